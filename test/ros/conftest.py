"""Fixtures of the node tests: ``harness_factory`` makes harnesses (``node_harness.Harness``) and
closes them after the test; ``node`` is a plain rclpy node; ``posed_frames`` renders a few frames of a drive with their truth."""

from __future__ import annotations

import pytest
import rclpy
from node_harness import Harness, closing_factory
from rclpy.context import Context


@pytest.fixture
def harness_factory():
    yield from closing_factory(Harness)


@pytest.fixture
def node():
    """A plain rclpy node in its own context (for publishers the outputs are sent through)."""
    context = Context()
    rclpy.init(context=context)
    n = rclpy.create_node("ficap_test_outputs", context=context)
    yield n
    n.destroy_node()
    rclpy.try_shutdown(context=context)


@pytest.fixture(scope="session")
def posed_frames():
    """(scene, [(truth frame, grey image)]): three 540p frames of a seeded drive (the cap in view,
    every frame posed), rendered once per test process."""
    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.tools.synth import (
        RenderConfig,
        default_scene,
        naturalistic_drive,
        render,
    )

    scene = default_scene("540p")
    frames = naturalistic_drive(90, fps=30.0, seed=4, scene=scene)[::30]
    model = nominal_model()
    return scene, [(f, render(model, scene.camera, f.T_cam_cap, RenderConfig(), seed=f.index).image)
                   for f in frames]
