"""Launch the live ERVA system on ROS 2 Jazzy: plant_sim_node, road_preview_node, nmpc_node.

    ros2 launch erva_ros erva.launch.py
    ros2 launch erva_ros erva.launch.py mode:=lockstep controller:=no_preview seed:=3

The same system `erva run` starts (without its monitor and recorder; record with
``ros2 bag record -s mcap /erva/state ...`` or ``ros2 run erva_ros recorder_node``).
Parameters: config/erva_paper.yaml (physical, ``/**``), config/nmpc.yaml (the
``nmpc_node`` section) and config/live.yaml, then the launch arguments below.
In lock-step mode every node runs on the plant's ``/clock`` (use_sim_time).

Importing this file needs no ROS (only erva_ros's core): the launch imports are inside
:func:`generate_launch_description`.
"""

import os

from erva_ros.core.node_params import launch_arguments, LOOP_NODES
from erva_ros.core.params import read_ros_params
from erva_ros.core.topics import NAMESPACE

#: Executables started (console scripts of setup.py), in start order.
NODES = LOOP_NODES
#: Parameter files of the package's config/ directory.
CONFIG_FILES = ('erva_paper.yaml', 'nmpc.yaml', 'live.yaml')
#: Launch arguments: (name, default, python type, description), from the nodes' schemas
#: (erva_ros/core/node_params.py; defaults: the shipped config files).
ARGUMENTS = (('namespace', NAMESPACE, str, 'namespace of the nodes and topics'),
             *launch_arguments())


def node_section(path: str, node: str) -> dict:
    """Return the ros__parameters of ``node`` in a params file (``node:``, ``/**/node``, ...).

    ``nmpc_node:`` only matches a node in the root namespace; reading the section
    here applies it to the namespaced node too.  The reader is erva_ros's own (the one
    `erva run` and the offline tools use).
    """
    return read_ros_params(path, node, wildcard=False, required=False)


def generate_launch_description():
    """Return the launch description of the live system."""
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument
    from launch.substitutions import LaunchConfiguration, PythonExpression
    from launch_ros.actions import Node
    from launch_ros.parameter_descriptions import ParameterValue

    config = os.path.join(get_package_share_directory('erva_ros'), 'config')
    paper, nmpc, live = (os.path.join(config, name) for name in CONFIG_FILES)
    declared = [DeclareLaunchArgument(name, default_value=default, description=doc)
                for name, default, _, doc in ARGUMENTS]
    overrides = {name: ParameterValue(LaunchConfiguration(name), value_type=kind)
                 for name, _, kind, _ in ARGUMENTS if name != 'namespace'}
    overrides['use_sim_time'] = ParameterValue(
        PythonExpression(["'", LaunchConfiguration('mode'), "' == 'lockstep'"]),
        value_type=bool)
    nodes = []
    for name in NODES:
        params = [paper, live]
        if name == 'nmpc_node':
            params.append(node_section(nmpc, 'nmpc_node'))
        params.append(overrides)
        nodes.append(Node(package='erva_ros', executable=name, name=name,
                          namespace=LaunchConfiguration('namespace'), parameters=params,
                          output='screen', emulate_tty=True))
    return LaunchDescription(declared + nodes)
