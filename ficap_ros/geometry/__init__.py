"""Geometry: rigid transforms, rotation and corner metrics, the camera model, the cap model.

The bottom layer of ficap_ros: it imports only ``errors``, ``files`` and ``stamps``.
"""
