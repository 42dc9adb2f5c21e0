"""
Launch the simulator and the estimator: the whole kf_train pipeline on simulated data.

    ros2 launch kf_train kf_train.launch.py
    ros2 launch kf_train kf_train.launch.py scenario:=car namespace:=train1
    ros2 launch kf_train kf_train.launch.py scenario:=rail
    ros2 launch kf_train kf_train.launch.py params_file:=my.yaml preset:=cv-position
    ros2 launch kf_train kf_train.launch.py --show-args

The launch arguments:

* ``params_file``: a ROS params file with ``simulator`` and ``estimator`` sections
  (default: the installed config/kf_train.yaml, every parameter at its default).
* ``namespace``: pushes both nodes, and their relative topics, into it; the file's
  sections apply to the namespaced nodes too (see kf_train/ros/launch_params.py).
* ``use_sim_time``: both nodes follow ``/clock`` (published by e.g. Gazebo); the
  simulator then also samples on that clock.
* ``managed``: true starts both nodes as managed (lifecycle) nodes, ``unconfigured``:
  drive them with ``ros2 lifecycle set`` or Nav2's lifecycle manager (docs/ros.md).
  Empty (default): the params file's ``managed`` (false in the installed one).
* ``scenario``: what the simulator simulates; ``preset``: the estimator's filter,
  by default the scenario's (every scenario is a preset of the same name). Empty:
  the params file's (the train when it names none). Choosing another one than the
  file's leaves out the file's values that depend on it (module doc of launch_params).
"""

from kf_train.ros import launch_params
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def _nodes(context):
    """Return the two nodes, their parameters resolved from the file and the arguments."""
    def argument(name):
        return LaunchConfiguration(name).perform(context)

    namespace = argument('namespace')
    params = launch_params.load_params_file(argument('params_file'))
    use_sim_time = launch_params.parse_bool('use_sim_time', argument('use_sim_time'))
    scenario = argument('scenario')
    preset = argument('preset') or scenario
    managed = argument('managed')
    return [
        Node(package='kf_train', executable='simulator', namespace=namespace,
             output='screen', parameters=[launch_params.with_managed(
                 launch_params.simulator_parameters(params, namespace, scenario,
                                                    use_sim_time), managed)]),
        Node(package='kf_train', executable='estimator', namespace=namespace,
             output='screen', parameters=[launch_params.with_managed(
                 launch_params.estimator_parameters(params, namespace, preset, use_sim_time),
                 managed)]),
    ]


def generate_launch_description():
    """Declare the arguments; the nodes are made once they are known."""
    default_params = PathJoinSubstitution(
        [FindPackageShare('kf_train'), 'config', 'kf_train.yaml'])
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS params file with simulator and estimator '
                              'sections'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='Namespace of both nodes and their topics'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              choices=['true', 'false', 'True', 'False'],
                              description='Follow /clock instead of the system clock'),
        DeclareLaunchArgument('scenario', default_value='',
                              description='What is simulated: train, car, car-exact, robot, '
                              "robot-exact, rail; empty: the params file's"),
        DeclareLaunchArgument('preset', default_value='',
                              description="The estimator's preset (or a preset .yaml "
                              "path); empty: the scenario's, else the params file's"),
        DeclareLaunchArgument('managed', default_value='',
                              choices=['', 'true', 'false', 'True', 'False'],
                              description='Start as managed (lifecycle) nodes, unconfigured; '
                              "empty: the params file's"),
        OpaqueFunction(function=_nodes),
    ])
