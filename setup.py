"""Build script for lidar_cam_calib (ament_python for colcon, plain pip for venvs)."""
import importlib.util
import os
import sys
from glob import glob

from setuptools import find_packages, setup

PACKAGE = "lidar_cam_calib"


def registry():
    """lidar_cam_calib/methods.py, read without importing the package (no numpy needed here)."""
    spec = importlib.util.spec_from_file_location("_lcc_methods", os.path.join(PACKAGE, "methods.py"))
    mod = importlib.util.module_from_spec(spec)
    sys.modules[spec.name] = mod  # dataclasses look their module up there
    spec.loader.exec_module(mod)
    return mod.METHODS


def data_files():
    out = [
        ("share/ament_index/resource_index/packages", ["resource/" + PACKAGE]),
        ("share/" + PACKAGE, ["package.xml"]),
        ("share/" + PACKAGE + "/config", sorted(glob("config/*.yaml"))),
        ("share/" + PACKAGE + "/config/scenarios", sorted(glob("config/scenarios/*.yaml"))),
    ]
    # Shipped bags: keep the directory structure (a rosbag2 bag is a directory).
    for root, _dirs, files in os.walk("bags"):
        if files:
            out.append((os.path.join("share", PACKAGE, root), sorted(os.path.join(root, f) for f in files)))
    return out


setup(
    name=PACKAGE,
    version="0.1.0",
    packages=find_packages(exclude=["test", "test.*"]),
    data_files=data_files(),
    # ROS (rclpy, message packages) comes from apt on a robot or from the
    # ros-jazzy-* wheels in dev/CI (requirements-ros-dev.txt); never pinned here.
    install_requires=[
        "numpy>=1.24",
        "scipy>=1.10",
        "opencv-python-headless>=4.8,<5",
        "pyyaml>=6",
        "rosbags>=0.10",
        "mcap>=1.1",
        # one BLAS thread during a calibration (lidar_cam_calib/core/threads.py); optional at import
        "threadpoolctl>=3",
    ],
    zip_safe=False,
    maintainer="lidar_cam_calib developers",
    maintainer_email="dev@lidar-cam-calib.invalid",
    description="Extrinsic calibration of range sensors and cameras for ROS 2 Jazzy",
    license="Apache-2.0",
    tests_require=["pytest"],
    entry_points={
        # one node executable per registered method (ros2 run lidar_cam_calib <executable>)
        "console_scripts": [f"{m.executable} = {m.node_module}:main" for m in registry().values()]
        + ["lidar-cam-calib = lidar_cam_calib.cli:main"],
    },
)
