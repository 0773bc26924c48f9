"""ficap_ros: Fi-Cap head-pose ground truth.

The core modules (cap_model, camera, detection, pose, metrics, calibration, messages, live, synth,
bag_io, ...) are free of ROS; only ``node.py`` and the ``ros_*.py`` modules use rclpy.
"""

__version__ = "0.3.4"
