"""``ficap_lifecycle_node``: ficap_node as a managed (lifecycle) node, for launch systems and
supervisors that bring nodes up in order (``ros2 lifecycle set /ficap_node configure``, then
``activate``). ``ficap_node`` stays the plain node, configured and active from its start.

The same node (``ficap_ros.ros.node.FicapNodeSteps``), its steps on the transitions:
    configure: declare and read the parameters (a bad one fails the transition with one log line),
        build the pipeline, load the calibration file, advertise the outputs and services;
    activate: subscribe (image, CameraInfo, reference); deactivate: unsubscribe;
    cleanup (and shutdown from inactive or active): stop the worker, remove outputs and services.
rclpy has no component container, so the node is not composable; this is the managed variant.
"""

from __future__ import annotations

from typing import Any, Callable

from rclpy.lifecycle import LifecycleNode, LifecycleState, TransitionCallbackReturn

from ficap_ros.errors import FicapError
from ficap_ros.ros import params as ros_params
from ficap_ros.ros.node import NODE_NAME, FicapNodeSteps
from ficap_ros.ros.spin import run_node

__all__ = ["FicapLifecycleNode", "main"]


class FicapLifecycleNode(FicapNodeSteps, LifecycleNode):
    """ficap_node as a lifecycle node (module docstring); named ``ficap_node`` like the plain one,
    so the same params files apply."""

    def __init__(self, **kwargs: Any) -> None:
        LifecycleNode.__init__(self, NODE_NAME, **kwargs)
        self._configured = False

    def _step(self, step: Callable[[], None], what: str) -> TransitionCallbackReturn:
        try:
            step()
        except FicapError as err:
            self.get_logger().error(f"{what} failed: {err}")
            return TransitionCallbackReturn.FAILURE
        return TransitionCallbackReturn.SUCCESS

    def on_configure(self, state: LifecycleState) -> TransitionCallbackReturn:
        result = self._step(self.configure, "configure")
        self._configured = result == TransitionCallbackReturn.SUCCESS
        return result

    def on_activate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._step(self.activate, "activate")

    def on_deactivate(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._step(self.deactivate, "deactivate")

    def on_cleanup(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._step(self._release, "cleanup")

    def on_shutdown(self, state: LifecycleState) -> TransitionCallbackReturn:
        return self._step(self._release, "shutdown")

    def _release(self) -> None:
        self.deactivate()
        if self._configured:
            self.cleanup()
            self._configured = False

    def destroy_node(self) -> None:
        """Release what the transitions made, then destroy the node."""
        self._release()
        super().destroy_node()


def main(args: list[str] | None = None) -> int:
    """Run ``ficap_lifecycle_node`` (unconfigured until told; ``--help`` as ficap_node's)."""
    return run_node(FicapLifecycleNode, "ficap_lifecycle_node", args,
                    usage=ros_params.usage(__doc__ or ""))


if __name__ == "__main__":
    raise SystemExit(main())
