"""The ROS skin: the node (plain and lifecycle), its inputs, outputs and TF, its parameters, rclpy
message conversions, the demo.

The only subpackage that imports rclpy; ``live`` (what the node does with one image) stays ROS-free
beside it. It imports only the layers below it (``tools``, ``io``, ``vision``, ``geometry``).
"""
