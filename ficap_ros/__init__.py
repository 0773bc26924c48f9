"""ficap_ros: Fi-Cap head-pose ground truth.

The core modules (cap_model, camera, detection, pose, metrics, calibration, synth, bag_io, ...) are
free of ROS; only ``node.py``, ``ros_msgs.py`` and ``ros_demo.py`` use rclpy.
"""

__version__ = "0.1.0"
