"""rtabmap_ros2: memory-managed appearance-based loop closure detection and multi-session graph SLAM.

Layers: ``core`` (the algorithm, ROS-free), ``io`` (bags, datasets, exports, command line),
``sim`` (the simulated multi-session building), ``ros`` (the thin rclpy layer).
"""

__version__ = "0.1.0"
