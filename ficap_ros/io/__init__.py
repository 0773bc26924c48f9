"""Files and recordings: image decoding, bags and videos as frame sources, damaged-bag salvage,
bag writing, ROS messages over their fields (rclpy or rosbags classes), the CameraInfo rule, the
output frames and TF tree, per-tag detections, labels and frame status.

No rclpy: it imports only ``vision``, ``geometry`` and the loose bottom modules.
"""
