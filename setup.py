"""ament_python / pip package definition for rtabmap_ros2."""
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "rtabmap_ros2"

setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*", "bench"]),
    data_files=[
        ("share/ament_index/resource_index/packages", [f"resource/{PACKAGE}"]),
        (f"share/{PACKAGE}", ["package.xml"]),
        (f"share/{PACKAGE}/config", glob("config/*.yaml") + glob("config/*.rviz")),
        (f"share/{PACKAGE}/launch", glob("launch/*.launch.py")),
    ],
    python_requires=">=3.10",
    install_requires=[
        "numpy>=1.24,<3",
        "scipy>=1.10,<2",
        # 4.x: OpenCV 5 moved several detectors out of the main wheel (LIBRARIES.md).
        "opencv-python-headless>=4.8,<5",
        "pyyaml>=6,<7",
        # Exact word search (vocabulary.index flat: knn_hamming / knn).
        "faiss-cpu>=1.8,<2",
        # The default word search, FLANN's randomized kd-trees (core/kdtree.py), compiled: 5k ORB
        # words built in 35 ms and 400 queries in 10 ms of CPU, against 18 s and 1.2 s as Python.
        # 0.60 is the first release with numpy 2.0 support.
        "numba>=0.60,<1",
        # Pose graph optimisation (Pose2/Pose3, LM, robust kernels), see bench/bench_optimizers.py.
        "gtsam>=4.2,<4.4",
        # ROS 1 / ROS 2 bag reading and writing without a ROS install.
        "rosbags>=0.10,<0.12",
        # Real photographs (skimage.data) to texture the simulated building.
        "scikit-image>=0.22,<0.27",
        "matplotlib>=3.7,<4",
        "tqdm>=4.60,<5",
    ],
    extras_require={
        "ros": ["ros-jazzy-rclpy[fastrtps]", "ros-jazzy-common-interfaces"],
        "test": ["pytest>=7", "ros-jazzy-rclpy[fastrtps]", "ros-jazzy-common-interfaces"],
    },
    zip_safe=True,
    maintainer="rtabmap_ros2 maintainers",
    description="RTAB-Map style memory-managed loop closure detection and multi-session graph SLAM for ROS 2",
    license="BSD-3-Clause",
    tests_require=["pytest"],
    entry_points={
        "console_scripts": [
            "rtabmap-ros2 = rtabmap_ros2.cli.cli:main",
            "rtabmap = rtabmap_ros2.ros.node:main",
        ],
    },
)
