"""Launch the ``rtabmap`` node next to a robot's drivers (a ROS 2 install: launch, launch_ros, tf2).

    ros2 launch rtabmap_ros2 rtabmap.launch.py \
        rgb_topic:=/camera/color/image_raw depth_topic:=/camera/aligned_depth_to_color/image_raw \
        camera_info_topic:=/camera/color/camera_info scan_topic:=/scan odom_topic:=/odom rviz:=true

Starts the node with the shipped parameters file (``config/rtabmap.yaml``, or ``params_file:=``),
the topic remappings below, ``respawn`` (the node exits non-zero on an unrecoverable error, e.g. an
unwritable database, and is restarted) and optionally RViz with ``config/rtabmap.rviz`` (map,
mapPath, mapGraph, TF). Sensor mounts come from TF (robot_state_publisher / static transforms) from
``frame_id``; ``qos`` and ``image_transport`` default to ``auto`` (matched to the drivers).
"""

import os

from ament_index_python.packages import get_package_share_directory
from launch import LaunchDescription
from launch.actions import DeclareLaunchArgument
from launch.conditions import IfCondition
from launch.substitutions import LaunchConfiguration
from launch_ros.actions import Node

PACKAGE = "rtabmap_ros2"

# (launch argument, default, description) of the node's inputs, remapped from its relative names.
TOPICS = [
    ("odom_topic", "/odom", "nav_msgs/Odometry of the robot's odometry", "odom"),
    ("scan_topic", "/scan", "sensor_msgs/LaserScan of the 2D laser", "scan"),
    ("rgb_topic", "/rgb/image", "colour image (raw; its /compressed variant is found too)", "rgb/image"),
    ("depth_topic", "/depth/image", "depth image registered to the colour one (raw or /compressedDepth)",
     "depth/image"),
    ("camera_info_topic", "/rgb/camera_info", "sensor_msgs/CameraInfo of the colour camera", "rgb/camera_info"),
]


def generate_launch_description():
    share = get_package_share_directory(PACKAGE)
    arguments = [
        DeclareLaunchArgument("params_file", default_value=os.path.join(share, "config", "rtabmap.yaml"),
                              description="ROS 2 parameters file of the node"),
        DeclareLaunchArgument("database_path", default_value="~/.ros/rtabmap_ros2.db",
                              description="map database (continued if it exists)"),
        DeclareLaunchArgument("frame_id", default_value="base_link", description="robot base frame"),
        DeclareLaunchArgument("qos", default_value="auto", description="auto, reliable or sensor_data"),
        DeclareLaunchArgument("image_transport", default_value="auto", description="auto, raw or compressed"),
        DeclareLaunchArgument("subscribe_scan", default_value="true", description="use the laser"),
        DeclareLaunchArgument("subscribe_rgb", default_value="true", description="use the colour image"),
        DeclareLaunchArgument("subscribe_depth", default_value="true", description="use the depth image"),
        DeclareLaunchArgument("respawn", default_value="true", description="restart the node if it exits"),
        DeclareLaunchArgument("rviz", default_value="false", description="start RViz with config/rtabmap.rviz"),
    ]
    arguments += [DeclareLaunchArgument(name, default_value=default, description=doc)
                  for name, default, doc, _ in TOPICS]
    node = Node(
        package=PACKAGE, executable="rtabmap", name="rtabmap", output="screen",
        respawn=LaunchConfiguration("respawn"), respawn_delay=2.0,
        parameters=[LaunchConfiguration("params_file"), {
            name: LaunchConfiguration(name)
            for name in ("database_path", "frame_id", "qos", "image_transport", "subscribe_scan",
                         "subscribe_rgb", "subscribe_depth")}],
        remappings=[(relative, LaunchConfiguration(name)) for name, _, _, relative in TOPICS])
    rviz = Node(package="rviz2", executable="rviz2", name="rviz2", output="screen",
                arguments=["-d", os.path.join(share, "config", "rtabmap.rviz")],
                condition=IfCondition(LaunchConfiguration("rviz")))
    return LaunchDescription([*arguments, node, rviz])
