"""ficap_ros: Fi-Cap head-pose ground truth.

The core modules (cap_model, camera, detection, pose, metrics, calibration, synth, bag_io, ...) never
import rclpy; only ``node.py`` and ``ros_msgs.py`` do.
"""

__version__ = "0.1.0"
