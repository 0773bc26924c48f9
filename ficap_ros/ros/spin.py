"""How ``ficap_node`` spins: its executor, and a node's run from ``rclpy.init`` to shutdown with
errors on one line (``ficap_ros.ros.node.main``)."""

from __future__ import annotations

import re
import sys
from typing import Callable

import rclpy
from rclpy.context import Context
from rclpy.executors import ExternalShutdownException, SingleThreadedExecutor
from rclpy.node import Node

from ficap_ros.errors import FicapError, missing_module
from ficap_ros.io.native_log import ThrottledStderr

__all__ = ["make_executor", "run_node", "wants_help"]


def make_executor(context: Context | None = None) -> SingleThreadedExecutor:
    """The executor ficap_node spins in (``main``, and the demo's node and player).

    Callbacks only fill the mailbox, publish or answer services (the worker thread does the
    processing), so one executor thread suffices. rclpy's MultiThreadedExecutor (Jazzy 7.1) is not
    used: while a callback waits in its thread pool, its spin loop yields the queued task again
    without waiting and re-submits it (ros2/rclpy#1452, fixed upstream by #1547), a busy loop that
    holds the GIL the pool thread and the worker need.
    """
    return SingleThreadedExecutor(context=context)


def _rcl_message(err: BaseException) -> str:
    """rcl's error as one line, without the C source locations it appends (``, at file.c:N``)."""
    text = " ".join(str(err).split())
    return re.sub(r",? at /\S+:\d+", "", text).strip()


def wants_help(args: list[str] | None) -> bool:
    """``-h`` or ``--help`` among the arguments before ``--ros-args`` (``sys.argv`` when None)."""
    argv = list(sys.argv[1:] if args is None else args)
    own = argv[:argv.index("--ros-args")] if "--ros-args" in argv else argv
    return any(a in ("-h", "--help") for a in own)


def run_node(make_node: Callable[[], Node], name: str, args: list[str] | None = None,
             usage: str = "") -> int:
    """Run a node (Jazzy's idiom: spin until Ctrl-C or external shutdown); the exit code.

    ``-h``/``--help`` prints ``usage`` and exits 0 without starting ROS. Bad ``--ros-args`` (a
    params file, a remap), ``FicapError``s at start and a missing optional module are one line on
    stderr after ``name:`` and exit 1.
    """
    from rclpy.impl.implementation_singleton import rclpy_implementation

    if wants_help(args):
        print(usage or f"usage: {name} [--ros-args ...]")
        return 0
    try:
        rclpy.init(args=args)
    except rclpy_implementation.RCLError as err:
        print(f"{name}: {_rcl_message(err)}", file=sys.stderr)
        return 1
    node: Node | None = None
    code = 0
    try:
        node = make_node()
        log = node.get_logger()
        # libjpeg/FFmpeg print per damaged frame on fd 2: through the logger, throttled.
        with ThrottledStderr(lambda text: log.warning(text)):
            rclpy.spin(node, make_executor())
    except (KeyboardInterrupt, ExternalShutdownException):
        pass
    except FicapError as err:
        print(f"{name}: {err}", file=sys.stderr)
        code = 1
    except ModuleNotFoundError as err:
        print(f"{name}: {missing_module(err)}", file=sys.stderr)
        code = 1
    finally:
        if node is not None:
            node.destroy_node()
        rclpy.try_shutdown()
    return code
