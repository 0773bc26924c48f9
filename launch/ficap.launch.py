"""Launch ficap_node for one rear camera.

    ros2 launch ficap_ros ficap.launch.py image:=/rear_cam/image_raw
    ros2 launch ficap_ros ficap.launch.py namespace:=rear image_transport:=compressed \
        params_file:=/path/to/my_ficap.yaml

The parameters come from ``params_file`` (default: the installed config/ficap.yaml, keyed ``/**`` so
it applies under any namespace); set ``output_frame`` and ``camera_mount`` there (a double array
cannot be passed as a launch argument). With ``image_transport:=compressed`` the node subscribes to
``<image>/compressed``. The CameraInfo is read beside the image topic (``/rear_cam/camera_info``
above, image_transport's rule) unless ``camera_info:=TOPIC`` names another. Two cameras:
``ficap_two_cameras.launch.py``.
"""

from launch.actions import DeclareLaunchArgument
from launch.substitutions import LaunchConfiguration, PathJoinSubstitution
from launch_ros.actions import Node
from launch_ros.substitutions import FindPackageShare

from launch import LaunchDescription


def generate_launch_description() -> LaunchDescription:
    default_params = PathJoinSubstitution([FindPackageShare("ficap_ros"), "config", "ficap.yaml"])
    return LaunchDescription([
        DeclareLaunchArgument("namespace", default_value="",
                              description="namespace of the node and its outputs"),
        DeclareLaunchArgument("node_name", default_value="ficap_node", description="node name"),
        DeclareLaunchArgument("image", default_value="/camera/image_raw",
                              description="image topic (sensor_msgs/Image; its /compressed for "
                                          "image_transport:=compressed)"),
        DeclareLaunchArgument("camera_info", default_value="",
                              description="sensor_msgs/CameraInfo topic ('' = beside the image "
                                          "topic: <its namespace>/camera_info)"),
        DeclareLaunchArgument("image_transport", default_value="raw",
                              description="raw or compressed"),
        DeclareLaunchArgument("params_file", default_value=default_params,
                              description="ficap_node parameters (ROS 2 params file)"),
        Node(
            package="ficap_ros",
            executable="ficap_node",
            name=LaunchConfiguration("node_name"),
            namespace=LaunchConfiguration("namespace"),
            output="screen",
            parameters=[
                LaunchConfiguration("params_file"),
                {"image_transport": LaunchConfiguration("image_transport"),
                 "camera_info_topic": LaunchConfiguration("camera_info")},
            ],
            remappings=[
                ("image", LaunchConfiguration("image")),
            ],
        ),
    ])
