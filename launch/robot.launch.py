"""One robot's nodes, in the robot's namespace, with a params file (a full ROS 2 install):

    ros2 launch csam_ros robot.launch.py namespace:=robot1 params_file:=/path/team.params.yaml

The same as ``smoother --ros-args -r __ns:=/robot1 --params-file team.params.yaml`` beside
``detections`` with the same arguments (the camera's tag detections as the smoother's
observations; ``detections:=false`` leaves it out where the robot's drivers publish
``features`` and ``rendezvous`` themselves). The params file's ``/**/smoother`` and
``/**/detections`` sections apply (share/csam_ros/config/team.params.yaml by default: a
two-robot team, robot1 and robot2).
"""

from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def generate_launch_description() -> LaunchDescription:
    team = PathJoinSubstitution([FindPackageShare("csam_ros"), "config", "team.params.yaml"])
    namespace = LaunchConfiguration("namespace")
    params_file = LaunchConfiguration("params_file")

    def robot_node(executable: str, **options: object) -> Node:
        return Node(
            package="csam_ros",
            executable=executable,
            name=executable,
            namespace=namespace,
            parameters=[params_file],
            output="screen",
            **options,
        )

    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "namespace",
                default_value="robot1",
                description="the robot's name: its nodes are /<namespace>/smoother and "
                "/<namespace>/detections",
            ),
            DeclareLaunchArgument(
                "params_file",
                default_value=team,
                description="ROS 2 params file with /**/smoother and /**/detections sections",
            ),
            DeclareLaunchArgument(
                "detections",
                default_value="true",
                description="start the detections node (false: the drivers publish features)",
            ),
            robot_node("smoother"),
            robot_node("detections", condition=IfCondition(LaunchConfiguration("detections"))),
        ]
    )
