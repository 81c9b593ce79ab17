"""Launch the live ERVA system on ROS 2 Jazzy: plant_sim_node, road_preview_node, nmpc_node.

    ros2 launch erva_ros erva.launch.py
    ros2 launch erva_ros erva.launch.py mode:=lockstep controller:=no_preview seed:=3
    ros2 launch erva_ros erva.launch.py autostart:=false     # managed by you

The nodes are lifecycle (managed) nodes.  With ``autostart:=true`` (default) this
file brings them up as `erva run` does: it configures them one by one, then activates
them in ACTIVATION_ORDER (the controller first, the time master last -- the road in
real time, the plant in lock-step).  With ``autostart:=false`` they stay unconfigured
for your lifecycle manager or ``ros2 lifecycle set /erva/<node> configure|activate``.

The same system `erva run` starts (without its monitor and recorder; record with
``ros2 bag record -s mcap /erva/state ...`` or ``ros2 run erva_ros recorder_node``).
Parameters: config/erva_paper.yaml (physical, ``/**``), config/nmpc.yaml (the
``nmpc_node`` section) and config/live.yaml, then the launch arguments below.
In lock-step mode every node runs on the plant's ``/clock`` (use_sim_time).

Importing this file needs no ROS (only erva_ros's core): the launch imports are inside
:func:`generate_launch_description`.
"""

import os

from erva_ros.core.settings.schemas import launch_arguments, LOOP_NODES
from erva_ros.session.run.run_config import ACTIVATION_ORDER
from erva_ros.core.model.params import read_ros_params
from erva_ros.core.topics import NAMESPACE

#: Executables started (console scripts of setup.py), in start order.
NODES = LOOP_NODES
#: Parameter files of the package's config/ directory.
CONFIG_FILES = ('erva_paper.yaml', 'nmpc.yaml', 'live.yaml')
#: Launch arguments: (name, default, python type, description), from the nodes' schemas
#: (erva_ros/core/settings/schemas.py; defaults: the shipped config files).
ARGUMENTS = (('namespace', NAMESPACE, str, 'namespace of the nodes and topics'),
             *launch_arguments())


def node_section(path: str, node: str) -> dict:
    """Return the ros__parameters of ``node`` in a params file (``node:``, ``/**/node``, ...).

    ``nmpc_node:`` only matches a node in the root namespace; reading the section
    here applies it to the namespaced node too.  The reader is erva_ros's own (the one
    `erva run` and the offline tools use).
    """
    return read_ros_params(path, node, wildcard=False, required=False)


def bring_up(nodes, order):
    """Return the event handlers that configure ``nodes`` in ``order``, then activate them.

    ``nodes``: {name: LifecycleNode action}.  Each step waits for the previous node to
    reach its state (configure: inactive; activate: active).
    """
    from launch.actions import EmitEvent, RegisterEventHandler
    from launch.event_handlers import OnProcessStart
    from launch.events import matches_action
    from launch_ros.event_handlers import OnStateTransition
    from launch_ros.events.lifecycle import ChangeState
    from lifecycle_msgs.msg import Transition

    def change(name, transition):
        return EmitEvent(event=ChangeState(lifecycle_node_matcher=matches_action(nodes[name]),
                                           transition_id=transition))
    steps = ([(name, Transition.TRANSITION_CONFIGURE, 'inactive') for name in order]
             + [(name, Transition.TRANSITION_ACTIVATE, 'active') for name in order])
    handlers = [RegisterEventHandler(OnProcessStart(target_action=nodes[order[0]],
                                                    on_start=[change(*steps[0][:2])]))]
    for (name, _, reached), (following, transition, _) in zip(steps, steps[1:]):
        handlers.append(RegisterEventHandler(OnStateTransition(
            target_lifecycle_node=nodes[name], goal_state=reached,
            entities=[change(following, transition)])))
    return handlers


def _nodes(context, paper, nmpc, live, overrides):
    """Return the nodes and, with autostart, their bring-up (an OpaqueFunction's body)."""
    from launch.substitutions import LaunchConfiguration
    from launch_ros.actions import LifecycleNode

    nodes = {}
    for name in NODES:
        params = [paper, live]
        if name == 'nmpc_node':
            params.append(node_section(nmpc, 'nmpc_node'))
        params.append({**overrides, 'autostart': False})   # this file drives them
        nodes[name] = LifecycleNode(package='erva_ros', executable=name, name=name,
                                    namespace=LaunchConfiguration('namespace'),
                                    parameters=params, output='screen', emulate_tty=True)
    actions = list(nodes.values())
    if LaunchConfiguration('autostart').perform(context).lower() in ('true', '1'):
        mode = LaunchConfiguration('mode').perform(context)
        actions += bring_up(nodes, [n for n in ACTIVATION_ORDER[mode] if n in nodes])
    return actions


def generate_launch_description():
    """Return the launch description of the live system."""
    from ament_index_python.packages import get_package_share_directory
    from launch import LaunchDescription
    from launch.actions import DeclareLaunchArgument, OpaqueFunction
    from launch.substitutions import LaunchConfiguration, PythonExpression
    from launch_ros.parameter_descriptions import ParameterValue

    config = os.path.join(get_package_share_directory('erva_ros'), 'config')
    paper, nmpc, live = (os.path.join(config, name) for name in CONFIG_FILES)
    declared = [DeclareLaunchArgument(name, default_value=default, description=doc)
                for name, default, _, doc in ARGUMENTS]
    overrides = {name: ParameterValue(LaunchConfiguration(name), value_type=kind)
                 for name, _, kind, _ in ARGUMENTS if name not in ('namespace', 'autostart')}
    overrides['use_sim_time'] = ParameterValue(
        PythonExpression(["'", LaunchConfiguration('mode'), "' == 'lockstep'"]),
        value_type=bool)
    return LaunchDescription(declared + [OpaqueFunction(
        function=_nodes, args=[paper, nmpc, live, overrides])])
