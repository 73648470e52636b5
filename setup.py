"""ament_python package csam_ros: `colcon build` on a ROS 2 Jazzy installation, or `make` here."""

from glob import glob

from setuptools import find_packages, setup

package_name = "csam_ros"

setup(
    name=package_name,
    version="0.1.0",
    packages=find_packages(include=[package_name, f"{package_name}.*"]),
    # the Fast DDS profile of live runs: found beside csam_ros/run/ros_env.py, and in share/
    # for nodes started by hand (FASTRTPS_DEFAULT_PROFILES_FILE)
    package_data={f"{package_name}.run": ["fastdds_profile.xml"]},
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{package_name}"]),
        (f"share/{package_name}", ["package.xml", f"{package_name}/run/fastdds_profile.xml"]),
        # scenario, config and ROS 2 params files (config/<setup>.params.yaml)
        (f"share/{package_name}/config", glob("config/*.yaml")),
        # ros2 launch csam_ros robot.launch.py / base_station.launch.py
        (f"share/{package_name}/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    zip_safe=True,
    maintainer="csam_ros maintainers",
    maintainer_email="maintainers@csam-ros.org",
    description="C-SAM multi-robot SLAM by square-root information smoothing, on ROS 2 Jazzy",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "simulator = csam_ros.nodes.simulator:main",
            "smoother = csam_ros.nodes.smoother:main",
            "merger = csam_ros.nodes.merger:main",
            "recorder = csam_ros.nodes.recorder:main",
            "player = csam_ros.nodes.player:main",
            "foxglove_bridge = csam_ros.nodes.foxglove_bridge:main",
            "detections = csam_ros.nodes.detections:main",
            "csam = csam_ros.cli:main",
        ],
    },
)
