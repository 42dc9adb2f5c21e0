"""
Launch the estimator alone, for recorded data (a bag) or a sensor of your own.

    ros2 launch kf_train estimator.launch.py measurement_topic:=/gnss/pose
    ros2 bag play --clock my_bag        # in another terminal: the bag drives /clock

The launch arguments:

* ``params_file``: a ROS params file with an ``estimator`` section (default: the
  installed config/kf_train.yaml).
* ``namespace``: pushes the node and its relative topics into it.
* ``use_sim_time``: true by default, for recorded data played with ``--clock``: the
  node clock then follows the bag, so the future-stamp check and ``/diagnostics``
  stamps use the recorded time, and a bag loop (the clock jumping back) resets the
  filter. Set it to false for a live sensor.
* ``preset``: the filter (default: the params file's, the train when it names none).
* ``managed``: true starts the estimator as a managed (lifecycle) node, ``unconfigured``
  (docs/ros.md); empty (default): the params file's ``managed``.
* ``measurement_topic`` / ``control_topic``: remap ``measurement`` and ``control``
  (the control only for presets with one: car, robot and their -exact variants).
"""

from kf_train.ros import launch_params
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def _estimator(context):
    """Return the estimator node, its parameters resolved from the file and arguments."""
    def argument(name):
        return LaunchConfiguration(name).perform(context)

    namespace = argument('namespace')
    params = launch_params.load_params_file(argument('params_file'))
    use_sim_time = launch_params.parse_bool('use_sim_time', argument('use_sim_time'))
    return [Node(
        package='kf_train', executable='estimator', namespace=namespace, output='screen',
        parameters=[launch_params.with_managed(launch_params.estimator_parameters(
            params, namespace, argument('preset'), use_sim_time), argument('managed'))],
        remappings=[('measurement', argument('measurement_topic')),
                    ('control', argument('control_topic'))])]


def generate_launch_description():
    """Declare the arguments; the node is made once they are known."""
    default_params = PathJoinSubstitution(
        [FindPackageShare('kf_train'), 'config', 'kf_train.yaml'])
    return LaunchDescription([
        DeclareLaunchArgument('params_file', default_value=default_params,
                              description='ROS params file with an estimator section'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='Namespace of the node and its topics'),
        DeclareLaunchArgument('use_sim_time', default_value='true',
                              choices=['true', 'false', 'True', 'False'],
                              description='Follow /clock (ros2 bag play --clock)'),
        DeclareLaunchArgument('preset', default_value='',
                              description="The estimator's preset (or a preset .yaml "
                              "path); empty: the params file's"),
        DeclareLaunchArgument('measurement_topic', default_value='measurement',
                              description='Topic of the measurements'),
        DeclareLaunchArgument('control_topic', default_value='control',
                              description='Topic of the control input (presets with one)'),
        DeclareLaunchArgument('managed', default_value='',
                              choices=['', 'true', 'false', 'True', 'False'],
                              description='Start as managed (lifecycle) nodes, unconfigured; '
                              "empty: the params file's"),
        OpaqueFunction(function=_estimator),
    ])
