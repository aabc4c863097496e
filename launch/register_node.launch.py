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

``rviz:=true`` also starts RViz with share/cgags_ros/rviz/cgags.rviz (the target cloud, the
aligned source, the pose, the candidates and TF) and has the node publish ~/aligned_cloud;
``rviz_fixed_frame`` (default ``map``) must be the target cloud's frame_id, the frame of
~/pose. RViz runs in the node's namespace and follows ``source_topic`` / ``target_topic``.

Every node of this launch (add the LiDAR driver here) gets Fast DDS's large-data profile,
share/cgags_ros/config/fastdds_large_data.xml, unless FASTRTPS_DEFAULT_PROFILES_FILE is
already set: without it, clouds above about half a megabyte are mostly lost between
processes (docs/transport.md). A driver started elsewhere needs it in its own shell.
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, SetEnvironmentVariable
from launch.conditions import IfCondition, UnlessCondition
from launch.substitutions import EnvironmentVariable, LaunchConfiguration, PythonExpression
from launch_ros.actions import Node
from launch_ros.parameter_descriptions import ParameterValue

NODE_NAME = 'register_node'
# The node's outputs (~/<name>) that rviz/cgags.rviz shows, under /register_node/: RViz gets
# them remapped into the launch's namespace.
RVIZ_NODE_TOPICS = ('pose', 'pose_with_covariance', 'aligned_cloud', 'candidates')


def sim_time() -> dict:
    """Return the use_sim_time parameter of the launch's nodes (true when playing a bag)."""
    return {'use_sim_time': ParameterValue(LaunchConfiguration('use_sim_time'), value_type=bool)}


def generate_launch_description() -> LaunchDescription:
    share = get_package_share_directory('cgags_ros')
    config = os.path.join(share, 'config')
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
        DeclareLaunchArgument('rviz', default_value='false',
                              description='true: also start RViz (rviz/cgags.rviz), and publish '
                                          '~/aligned_cloud for it.'),
        DeclareLaunchArgument('rviz_fixed_frame', default_value='map',
                              description="RViz's fixed frame: the target cloud's frame_id."),
    ]
    rviz = LaunchConfiguration('rviz')

    def register_node(condition, outputs):
        return Node(
            package='cgags_ros',
            executable='register_node',
            name=NODE_NAME,
            namespace=LaunchConfiguration('namespace'),
            output='screen',
            emulate_tty=True,
            parameters=[defaults, LaunchConfiguration('params_file'),
                        {**sim_time(),
                         'autostart': ParameterValue(PythonExpression(
                             ["'", LaunchConfiguration('use_lifecycle_manager'),
                              "'.lower() != 'true'"]), value_type=bool),
                         **outputs}],
            remappings=[('source_cloud', LaunchConfiguration('source_topic')),
                        ('target_cloud', LaunchConfiguration('target_topic'))],
            condition=condition,
        )

    # One of the two runs: with RViz the node also publishes the aligned source it shows.
    nodes = [register_node(UnlessCondition(rviz), {}),
             register_node(IfCondition(rviz), {'output.publish_aligned_cloud': True})]
    viewer = Node(
        package='rviz2',
        executable='rviz2',
        name='rviz2',
        namespace=LaunchConfiguration('namespace'),
        output='screen',
        arguments=['-d', os.path.join(share, 'rviz', 'cgags.rviz'),
                   '-f', LaunchConfiguration('rviz_fixed_frame')],
        parameters=[sim_time()],
        # The config names absolute topics; a relative replacement resolves in the namespace.
        remappings=[('/source_cloud', LaunchConfiguration('source_topic')),
                    ('/target_cloud', LaunchConfiguration('target_topic'))]
        + [(f'/{NODE_NAME}/{name}', f'{NODE_NAME}/{name}') for name in RVIZ_NODE_TOPICS],
        condition=IfCondition(rviz),
    )
    return LaunchDescription(args + [profile, *nodes, viewer])
