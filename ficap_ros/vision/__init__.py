"""Vision: one frame in, one cap pose out (detection, corners, tracking, pose, uncertainty,
calibration solvers).

No files, no recordings, no ROS: it imports only ``geometry`` and the loose bottom modules.
"""
