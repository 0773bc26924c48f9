"""Offline jobs: replay, evaluation, the as-built model, the printable kit, the renderer, fleets.

No rclpy: it imports only ``io``, ``vision``, ``geometry`` and the loose bottom modules.
"""
