"""ament_python package: builds with colcon in a Jazzy workspace and installs with pip."""

from glob import glob

from setuptools import find_packages, setup

package_name = "ficap_ros"

setup(
    name=package_name,
    version="0.3.4",
    packages=find_packages(exclude=["test", "test.*", "benchmarks"]),
    # The vendored message definitions (ficap_ros/interfaces/README.md): labels.mcap's detections.
    package_data={package_name: ["py.typed", "data/*", "interfaces/README.md",
                                 "interfaces/*/LICENSE", "interfaces/*/msg/*.msg"]},
    data_files=[
        ("share/ament_index/resource_index/packages", ["resource/" + package_name]),
        ("share/" + package_name, ["package.xml"]),
        ("share/" + package_name + "/config", glob("config/*")),
        ("share/" + package_name + "/launch", glob("launch/*.launch.py")),
    ],
    install_requires=["setuptools"],
    # Runtime dependencies come from package.xml (rosdep) or requirements.txt (pip, pinned);
    # the extras mirror requirements-extras.txt and requirements-test.txt.
    extras_require={"ray": ["ray==2.60.0"],
                    "apriltag": ["pupil-apriltags==1.0.4.post11"],
                    "test": ["pytest", "pytest-xdist", "pytest-timeout", "hypothesis",
                             "mcap-ros2-support"]},
    zip_safe=True,
    maintainer="ficap_ros maintainers",
    maintainer_email="maintainers@users.noreply.h-seed-c0fda0a4.example",
    description="Fi-Cap head-pose ground truth for ROS 2 Jazzy.",
    license="BSD-3-Clause",
    python_requires=">=3.10",
    entry_points={
        "console_scripts": [
            "ficap = ficap_ros.cli.main:main",
            "ficap_node = ficap_ros.ros.node:main",
            "ficap_lifecycle_node = ficap_ros.ros.lifecycle:main",
        ],
    },
)
