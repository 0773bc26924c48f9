"""ficap_ros.ros.spin: the executor ficap_node spins in, and a node's run from ``rclpy.init`` to
shutdown: bad ``--ros-args`` and errors at start are one line after the node's name and exit 1,
an external shutdown ends the run cleanly (exit 0, the node destroyed, the context shut down)."""

from __future__ import annotations

import pytest
import rclpy
from rclpy.context import Context
from rclpy.executors import SingleThreadedExecutor

from ficap_ros.errors import ModelError
from ficap_ros.ros.spin import _rcl_message, make_executor, run_node


def test_unparsable_ros_args_are_one_line_not_a_traceback(tmp_path) -> None:
    """A missing or malformed params file (refused by the guarded loader before rcl reads it), or
    a bad remap (refused by rcl in rclpy.init): the node says so in one line of its own (rcl
    logs one more for a remap) and exits 1."""
    import os
    import subprocess
    import sys

    bad = tmp_path / "bad.yaml"
    bad.write_text("garbage: [\n")
    for ros_args, says in ((["--params-file", str(tmp_path / "none.yaml")], "No such file"),
                           (["--params-file", str(bad)], "params file"),
                           (["-r", "badremap"], "remap rule")):
        run = subprocess.run([sys.executable, "-m", "ficap_ros.ros.node", "--ros-args", *ros_args],
                             capture_output=True, text=True, timeout=120, env=dict(os.environ))
        assert run.returncode == 1, run.stderr
        assert "Traceback" not in run.stderr, run.stderr
        ours = [ln for ln in run.stderr.splitlines() if ln.startswith("ficap_node:")]
        assert len(ours) == 1 and says in ours[0] and "parser.c" not in ours[0], run.stderr


def test_bad_ros_args_in_process_are_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    made = []
    code = run_node(lambda: made.append(1), "my_node", ["--ros-args", "-r", "badremap"])
    assert code == 1 and made == []  # rclpy.init refused: no node was made
    ours = [ln for ln in capsys.readouterr().err.splitlines() if ln.startswith("my_node:")]
    assert len(ours) == 1 and "remap rule" in ours[0] and ".c:" not in ours[0]
    assert not rclpy.ok()


def test_an_error_at_start_is_one_line_and_rclpy_is_shut_down(
        capsys: pytest.CaptureFixture[str]) -> None:
    def refuse():  # noqa: ANN202
        raise ModelError("model_file cap.yaml: no tags")

    assert run_node(refuse, "ficap_node", []) == 1
    assert capsys.readouterr().err.strip().splitlines()[-1] == "ficap_node: model_file cap.yaml: no tags"
    assert not rclpy.ok()


def test_an_external_shutdown_ends_the_run_cleanly() -> None:
    """A node that shuts rclpy down from a timer (as ``ros2 lifecycle`` or a launch file's
    shutdown would from outside): the spin ends, the node is destroyed, exit 0."""
    made = []

    def make():  # noqa: ANN202
        node = rclpy.create_node("ficap_spin_test")
        node.create_timer(0.05, lambda: rclpy.shutdown())
        made.append(node)
        return node

    assert run_node(make, "ficap_spin_test", []) == 0
    assert len(made) == 1 and not rclpy.ok()
    with pytest.raises(RuntimeError, match="destruction was requested"):
        made[0].get_name()  # destroyed: its handle is gone


def test_the_executor_is_single_threaded_on_the_given_context() -> None:
    context = Context()
    rclpy.init(context=context)
    try:
        executor = make_executor(context)
        assert type(executor) is SingleThreadedExecutor and executor.context is context
        executor.shutdown()
    finally:
        rclpy.try_shutdown(context=context)


def test_rcl_messages_lose_their_source_locations() -> None:
    err = RuntimeError("Couldn't parse remap rule: 'badremap'. Error: Expected lexeme type (19), "
                       "got (34) at index 8, at /tmp/ws/src/rcl/rcl/src/rcl/arguments.c:1234\n"
                       "  more, at /opt/ros/src/rcl/lexer.c:56")
    assert _rcl_message(err) == ("Couldn't parse remap rule: 'badremap'. Error: Expected lexeme "
                                 "type (19), got (34) at index 8 more")


def test_help_is_asked_before_ros_args_only() -> None:
    from ficap_ros.ros.spin import wants_help

    assert wants_help(["--help"]) and wants_help(["-h", "--ros-args", "-p", "a:=1"])
    assert not wants_help([]) and not wants_help(["--ros-args", "-r", "__node:=-h"])


def test_help_prints_usage_and_starts_nothing(capsys: pytest.CaptureFixture[str]) -> None:
    made = []
    assert run_node(lambda: made.append(1), "my_node", ["--help"], usage="usage: my_node ...") == 0
    assert made == [] and capsys.readouterr().out == "usage: my_node ...\n"
    assert not rclpy.ok()


def test_a_missing_optional_module_at_start_is_one_line(capsys: pytest.CaptureFixture[str]) -> None:
    def needs_ray():  # noqa: ANN202
        raise ModuleNotFoundError("No module named 'ray'", name="ray")

    assert run_node(needs_ray, "ficap_node", []) == 1
    err = capsys.readouterr().err
    assert err.strip().splitlines()[-1] == "ficap_node: the Python module ray is not installed (pip install ray)"
    assert "Traceback" not in err and not rclpy.ok()


def test_params_files_are_read_through_the_guarded_loader(tmp_path, capsys) -> None:  # noqa: ANN001
    """A params file that is a FIFO (rcl would block reading it for ever), /dev/zero, or YAML
    with an alias bomb: one line naming it, before rcl parses anything."""
    import os

    from ficap_ros.ros.node import FicapNode
    from ficap_ros.ros.spin import params_files, run_node

    assert params_files(["ficap_node", "--ros-args", "-p", "a:=1", "--params-file", "x.yaml",
                         "--", "--params-file", "not_ros.yaml"]) == ["x.yaml"]
    fifo = tmp_path / "params.fifo"
    os.mkfifo(fifo)
    bomb = tmp_path / "bomb.yaml"
    bomb.write_text("a: &a [1, 1]\nb: [*a, *a]\n")
    for path, says in ((fifo, "not a regular file"), ("/dev/zero", "not a regular file"),
                       (bomb, "aliases")):
        code = run_node(FicapNode, "ficap_node", ["ficap_node", "--ros-args", "--params-file",
                                                  str(path)])
        err = capsys.readouterr().err.strip().splitlines()
        assert code == 1 and len(err) == 1 and says in err[0], err
        assert err[0].startswith(f"ficap_node: params file {path} ")
