"""RViz2 with the fullperc view (config/fullperc.rviz; docs/nodes.md "TF and RViz2"), when rviz2 is installed.

    ros2 launch fullperc_eval rviz.launch.py            # next to `make demo` or demo.launch.py

Without rviz2 (the PyPI-wheel ROS has none) it logs where to get it and starts nothing. ``rviz_config``
overrides the config file.
"""

import os
import shutil

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument, LogInfo
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node


def generate_launch_description():
    default = os.path.join(get_package_share_directory("fullperc_eval"), "config", "fullperc.rviz")
    arg = DeclareLaunchArgument("rviz_config", default_value=default, description="RViz2 config file")
    if shutil.which("rviz2") is None:
        return LaunchDescription([arg, LogInfo(msg="rviz2 not found: install ros-jazzy-rviz2 (a system ROS 2 "
                                               "Jazzy) to see fullperc in RViz; nothing started")])
    return LaunchDescription([arg, Node(package="rviz2", executable="rviz2", name="rviz2", output="screen",
                                        arguments=["-d", LaunchConfiguration("rviz_config")])])
