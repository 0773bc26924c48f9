"""Example: two rear cameras looking at the same cap, each with its own ficap_node.

    ros2 launch ficap_ros ficap_two_cameras.launch.py

Each node runs in its own namespace (``rear_left``, ``rear_right``: topics ``/rear_left/head_pose``
...), reads the shared params file, and gets its own ``camera_mount`` (the camera's optical frame in
``base_link``, x y z qx qy qz qw as static_transform_publisher takes them), so both publish head
poses in ``base_link`` that can be compared or fused; each reads the CameraInfo beside its image
topic (``/rear_left/camera_info``). The mounts below are an example (cameras
0.55 m behind and 0.2 m to either side of base_link's origin at 1.25 m, turned 15 deg inwards,
pitched down 10 deg); replace them with the car's. ``diagnostics.hardware_id`` tells the cameras
apart on /diagnostics.
"""

from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription

#: (namespace, image topic, camera_mount [x y z qx qy qz qw]).
CAMERAS = (
    ("rear_left", "/rear_left/image_raw", [-0.55, 0.2, 1.25, -0.466338, 0.607744, -0.509958, 0.391304]),
    ("rear_right", "/rear_right/image_raw", [-0.55, -0.2, 1.25, -0.607744, 0.466338, -0.391304, 0.509958]),
)


def generate_launch_description() -> LaunchDescription:
    default_params = PathJoinSubstitution([FindPackageShare("ficap_ros"), "config", "ficap.yaml"])
    actions = [
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="ficap_node parameters shared by both nodes"),
    ]
    for namespace, image, mount in CAMERAS:
        actions.append(Node(
            package="ficap_ros",
            executable="ficap_node",
            name="ficap_node",
            namespace=namespace,
            output="screen",
            parameters=[
                LaunchConfiguration("params_file"),
                {
                    "output_frame": "base_link",
                    "camera_mount": mount,
                    "diagnostics.hardware_id": namespace,
                },
            ],
            remappings=[
                ("image", image),
            ],
        ))
    return LaunchDescription(actions)
