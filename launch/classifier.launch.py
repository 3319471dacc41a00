"""Start the Point-GN classifier node: `ros2 launch point_gn_ros classifier.launch.py`.

Arguments (all optional):
  params_file   YAML parameters (default: the package's config/classifier.yaml, keyed `/**`)
  namespace     namespace of the node (its topics become <namespace>/point_gn_classifier/...)
  node_name     node name (default point_gn_classifier)
  bank_path     feature bank .npz; '' keeps the params file's value
  input_topics  PointCloud2 topics, YAML list ("[front/objects, rear/objects]"); '' keeps the
                params file's value
  segment_field      integer point field that splits a message into objects; 'none' = each
                     message is one object; '' keeps the params file's value
  up_axis            auto, z, -z, y, -y, x or -x; '' keeps the params file's value
  unknown_threshold  top-1 scores below it are unknown (0 off, < 0 the bank's calibrated
                     one); '' keeps the params file's value
  qos_reliability    input QoS: auto, reliable or best_effort; '' keeps the params file's
  autostart     true: configure + activate by itself; false: wait for a lifecycle manager
  use_sim_time  true when replaying a bag with /clock
  log_level     info, debug, warn, ...

Example: ros2 launch point_gn_ros classifier.launch.py namespace:=perception
         bank_path:=/data/my_bank.npz input_topics:='[camera/objects]'
         segment_field:=label up_axis:=z unknown_threshold:=0.3 qos_reliability:=best_effort

Stop it with Ctrl-C (SIGINT) or `kill -INT`. `kill -TERM` on `ros2 launch` ends launch at once
without stopping its processes; the node notices its parent's death and stops cleanly too.
"""

from pathlib import Path

from ament_index_python.packages import get_package_share_directory
from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node
import yaml

PACKAGE = 'point_gn_ros'


def _node(context: LaunchContext) -> list:
    arg = lambda name: LaunchConfiguration(name).perform(context)  # noqa: E731
    params: list = [arg('params_file')]
    overrides = {'autostart': arg('autostart').lower() == 'true',
                 'allow_parameter_changes': arg('allow_parameter_changes').lower() == 'true',
                 'use_sim_time': arg('use_sim_time').lower() == 'true'}
    if arg('bank_path'):
        overrides['bank_path'] = arg('bank_path')
    if arg('input_topics'):
        topics = yaml.safe_load(arg('input_topics'))
        overrides['input_topics'] = [topics] if isinstance(topics, str) else list(topics)
    for name in ('segment_field', 'up_axis', 'qos_reliability'):
        if arg(name):
            overrides[name] = '' if arg(name) == 'none' and name == 'segment_field' else arg(name)
    if arg('unknown_threshold'):
        overrides['unknown_threshold'] = float(arg('unknown_threshold'))
    params.append(overrides)
    return [Node(package=PACKAGE, executable='classifier_node', name=arg('node_name'),
                 namespace=arg('namespace'), parameters=params, output='screen',
                 arguments=['--ros-args', '--log-level', arg('log_level')],
                 # launch exits on SIGTERM without stopping its processes: the node then
                 # stops by itself (node/parent_death.py)
                 additional_env={'POINT_GN_EXIT_WITH_PARENT': '1'})]


def generate_launch_description() -> LaunchDescription:
    share = Path(get_package_share_directory(PACKAGE))
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=str(share / 'config' /
                                                               'classifier.yaml'),
                              description='YAML parameter file (keyed /**)'),
        DeclareLaunchArgument('namespace', default_value='', description='node namespace'),
        DeclareLaunchArgument('node_name', default_value='point_gn_classifier',
                              description='node name'),
        DeclareLaunchArgument('bank_path', default_value='',
                              description="feature bank .npz ('' = params file's)"),
        DeclareLaunchArgument('input_topics', default_value='',
                              description="YAML list of PointCloud2 topics ('' = params "
                                          "file's)"),
        DeclareLaunchArgument('segment_field', default_value='',
                              description="segment field; 'none' = one object a message; '' "
                                          "= params file's"),
        DeclareLaunchArgument('up_axis', default_value='',
                              description="auto, z, -z, y, -y, x, -x ('' = params file's)"),
        DeclareLaunchArgument('unknown_threshold', default_value='',
                              description="open-set threshold ('' = params file's)"),
        DeclareLaunchArgument('qos_reliability', default_value='',
                              description="input QoS: auto, reliable, best_effort ('' = "
                                          "params file's)"),
        DeclareLaunchArgument('allow_parameter_changes', default_value='false',
                              description='let ros2 param set change the live parameters'),
        DeclareLaunchArgument('autostart', default_value='true',
                              description='walk the lifecycle to active by itself'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='use /clock (bag replay)'),
        DeclareLaunchArgument('log_level', default_value='info', description='log level'),
        OpaqueFunction(function=_node),
    ])
