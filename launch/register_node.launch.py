"""
Launch the registration node with the package's default parameters.

    ros2 launch cgags_ros register_node.launch.py \
        source_topic:=/velodyne_points target_topic:=/map_cloud \
        params_file:=/path/to/my.yaml

The YAML (default: share/cgags_ros/config/register_node.yaml, generated from the config
dataclasses) is loaded first, so any key in ``params_file`` overrides it.

``use_lifecycle_manager:=true`` leaves the (lifecycle) node unconfigured (``autostart:
false``) for a lifecycle manager to bring up, e.g. nav2_lifecycle_manager with
``node_names: ['register_node']`` (docs/lifecycle.md); by default it configures and
activates itself.

Every node of this launch (add the LiDAR driver here) gets Fast DDS's large-data profile,
share/cgags_ros/config/fastdds_large_data.xml, unless FASTRTPS_DEFAULT_PROFILES_FILE is
already set: without it, clouds above about half a megabyte are mostly lost between
processes (docs/transport.md). A driver started elsewhere needs it in its own shell.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
from launch.substitutions import EnvironmentVariable, LaunchConfiguration, PythonExpression
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue


def generate_launch_description() -> LaunchDescription:
    config = os.path.join(get_package_share_directory('cgags_ros'), 'config')
    defaults = os.path.join(config, 'register_node.yaml')
    profile = SetEnvironmentVariable(
        'FASTRTPS_DEFAULT_PROFILES_FILE',
        EnvironmentVariable('FASTRTPS_DEFAULT_PROFILES_FILE',
                            default_value=os.path.join(config, 'fastdds_large_data.xml')))
    args = [
        DeclareLaunchArgument('source_topic', default_value='source_cloud',
                              description='PointCloud2 to align (sensor frame).'),
        DeclareLaunchArgument('target_topic', default_value='target_cloud',
                              description='PointCloud2 reference (map or previous scan).'),
        DeclareLaunchArgument('params_file', default_value=defaults,
                              description='YAML with register_node parameters.'),
        DeclareLaunchArgument('use_sim_time', default_value='false',
                              description='Use /clock (true when playing a bag).'),
        DeclareLaunchArgument('namespace', default_value='',
                              description='Namespace of the node and its topics.'),
        DeclareLaunchArgument('use_lifecycle_manager', default_value='false',
                              description='true: a lifecycle manager configures and '
                                          'activates the node (autostart false).'),
    ]
    node = Node(
        package='cgags_ros',
        executable='register_node',
        name='register_node',
        namespace=LaunchConfiguration('namespace'),
        output='screen',
        emulate_tty=True,
        parameters=[defaults, LaunchConfiguration('params_file'),
                    {'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'),
                                                    value_type=bool),
                     'autostart': ParameterValue(PythonExpression(
                         ["'", LaunchConfiguration('use_lifecycle_manager'),
                          "'.lower() != 'true'"]), value_type=bool)}],
        remappings=[('source_cloud', LaunchConfiguration('source_topic')),
                    ('target_cloud', LaunchConfiguration('target_topic'))],
    )
    return LaunchDescription(args + [profile, node])
