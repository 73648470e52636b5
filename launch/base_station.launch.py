"""The base station: the merger, and a recorder of what reaches the base station (a full ROS 2
install):

    ros2 launch csam_ros base_station.launch.py params_file:=/path/team.params.yaml

The same as ``merger --ros-args --params-file team.params.yaml`` beside ``recorder -o BAG
--topics ...``: the recorder records each robot's local map updates and rendezvous poses and
the global topics (csam_ros.ros.topics.base_station_topics), of the robots named by
``robots`` (comma-separated; by default the params file's merger ``robots``) into ``bag`` (by
default runs/base_station-<time>); ``record:=false`` leaves it out.
"""

from launch import LaunchContext, LaunchDescription
from launch.actions import DeclareLaunchArgument, OpaqueFunction
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare


def _recorder(context: LaunchContext) -> list[Node]:
    from csam_ros.run.params_files import base_station_recorder_arguments

    def argument(name: str) -> str:
        return LaunchConfiguration(name).perform(context)

    arguments = base_station_recorder_arguments(
        argument("params_file"), argument("robots"), argument("bag")
    )
    return [
        Node(
            package="csam_ros",
            executable="recorder",
            arguments=arguments,
            output="screen",
            condition=IfCondition(LaunchConfiguration("record")),
        )
    ]


def generate_launch_description() -> LaunchDescription:
    team = PathJoinSubstitution([FindPackageShare("csam_ros"), "config", "team.params.yaml"])
    return LaunchDescription(
        [
            DeclareLaunchArgument(
                "params_file",
                default_value=team,
                description="ROS 2 params file with a merger section",
            ),
            DeclareLaunchArgument(
                "robots",
                default_value="",
                description="comma-separated robot names whose topics the recorder records "
                "(default: the params file's merger robots)",
            ),
            DeclareLaunchArgument(
                "bag", default_value="", description="new bag folder (runs/base_station-<time>)"
            ),
            DeclareLaunchArgument(
                "record", default_value="true", description="record (true) or not (false)"
            ),
            Node(
                package="csam_ros",
                executable="merger",
                name="merger",
                parameters=[LaunchConfiguration("params_file")],
                output="screen",
            ),
            OpaqueFunction(function=_recorder),
        ]
    )
