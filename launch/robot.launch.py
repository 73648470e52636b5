"""One robot's smoother, in the robot's namespace, with a params file (a full ROS 2 install):

    ros2 launch csam_ros robot.launch.py namespace:=robot1 params_file:=/path/team.params.yaml

The same as ``smoother --ros-args -r __ns:=/robot1 --params-file team.params.yaml``. The params
file's ``/**/smoother`` section applies (share/csam_ros/config/team.params.yaml by default: a
two-robot team, robot1 and robot2); its sensor topics are ``/<namespace>/odom``,
``/<namespace>/features`` (or ``feature_points``) and ``/<namespace>/rendezvous``.
"""

# ruff: noqa: I001 - `launch` is ROS 2's package, not this launch/ folder (ruff takes it for ours)
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description() -> LaunchDescription:
    team = PathJoinSubstitution([FindPackageShare("csam_ros"), "config", "team.params.yaml"])
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "namespace",
                default_value="robot1",
                description="the robot's name: its smoother is /<namespace>/smoother",
            ),
            DeclareLaunchArgument(
                "params_file",
                default_value=team,
                description="ROS 2 params file with a /**/smoother section",
            ),
            Node(
                package="csam_ros",
                executable="smoother",
                name="smoother",
                namespace=LaunchConfiguration("namespace"),
                parameters=[LaunchConfiguration("params_file")],
                output="screen",
            ),
        ]
    )
