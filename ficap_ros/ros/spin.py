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
from ficap_ros.process import freeze_start_up

__all__ = ["make_executor", "run_node", "wants_help", "params_files", "check_params_files"]


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


def params_files(args: list[str]) -> list[str]:
    """The ``--params-file FILE`` arguments of a command line's ``--ros-args`` sections."""
    files, in_ros = [], False
    for i, arg in enumerate(args):
        if arg == "--ros-args":
            in_ros = True
        elif arg == "--":
            in_ros = False
        elif in_ros and arg == "--params-file" and i + 1 < len(args):
            files.append(args[i + 1])
    return files


def check_params_files(args: list[str]) -> None:
    """Read every params file of the command line through the guarded loader
    (``files.load_yaml``: a regular file, not too large, YAML without aliases or deep nesting)
    before rcl parses it: a FIFO would block it for ever, a huge or hostile file cost it memory.

    Raises:
        ConfigError: naming the file.
    """
    from ficap_ros.errors import ConfigError
    from ficap_ros.files import load_yaml

    for path in params_files(args):
        load_yaml(path, "params file", ConfigError)


def run_node(make_node: Callable[[], Node], name: str, args: list[str] | None = None,
             usage: str = "") -> int:
    """Run a node (Jazzy's idiom: spin until Ctrl-C or external shutdown); the exit code.

    ``-h``/``--help`` prints ``usage`` and exits 0 without starting ROS. Bad ``--ros-args`` (a
    params file, a remap), ``FicapError``s at start and a missing optional module are one line on
    stderr after ``name:`` and exit 1; params files are read through the guarded loader first
    (``check_params_files``).
    """
    from rclpy.impl.implementation_singleton import rclpy_implementation

    if wants_help(args):
        print(usage or f"usage: {name} [--ros-args ...]")
        return 0
    try:
        check_params_files(sys.argv if args is None else args)
    except FicapError as err:
        print(f"{name}: {err}", file=sys.stderr)
        return 1
    try:
        rclpy.init(args=args)
    except rclpy_implementation.RCLError as err:
        print(f"{name}: {_rcl_message(err)}", file=sys.stderr)
        return 1
    node: Node | None = None
    code = 0
    try:
        node = make_node()
        freeze_start_up()  # the imports and warmed kernels: no full collection walks them mid-stream
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
