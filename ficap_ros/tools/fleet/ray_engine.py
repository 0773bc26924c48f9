"""The fleet's Ray engine: the segments of any number of recordings spread over one Ray cluster's
CPUs, each recording's results back in order.

With Ray (``--ray``: an embedded single-machine Ray kept on loopback; ``--ray-address``: an existing
cluster), every recording is cut into the replay's fixed segments (``replay.SEGMENT_FRAMES``, at
whose first frames tracking restarts whatever the engine, each with its look-ahead frame where
frames are solved with their next one: ``replay.segments``), so the labels are byte-identical to
``--jobs 1``. The driver reads the recordings and ships the undecoded frames through Ray's object
store, so workers need ficap_ros installed but no access to the inputs or outputs; only the driver
reads and writes files. A segment whose worker dies is retried (``retries``). Nothing imports ray
until an engine is made.

No wait is unbounded: a new engine runs one small task first and fails in one line when no worker
answers within ``START_TIMEOUT_S`` (workers that cannot start, e.g. out of address space), and a
segment that does not come back within ``SEGMENT_TIMEOUT_S`` fails its recording.
"""

from __future__ import annotations

import os
import threading
from collections import deque
from typing import Any, Callable, Iterable, Iterator

from ficap_ros.errors import ConfigError, WorkerError
from ficap_ros.geometry.camera import CameraTiming
from ficap_ros.geometry.cap_model import CapModel
from ficap_ros.io.sources import RawFrame
from ficap_ros.tools import replay
from ficap_ros.tools.fleet.fingerprints import settings_key
from ficap_ros.vision.detector import DetectorConfig
from ficap_ros.vision.pose import PoseConfig

__all__ = ["RayEngine", "ray_segment", "START_TIMEOUT_S", "SEGMENT_TIMEOUT_S"]

#: Longest wait for a new engine's first task: its workers start (importing numpy, OpenCV and
#: the pipeline) well within it, on a loaded machine too.
START_TIMEOUT_S = 120.0
#: Longest wait for one segment's frames, queueing included: many times what 128 frames of the
#: slowest settings take.
SEGMENT_TIMEOUT_S = 1800.0


def _probe() -> int:
    """The first task of an engine: a worker that runs it has started."""
    return os.getpid()

#: What this Ray worker process's pipeline labels with (``settings_key``).
_WORKER_KEY: Any = None


def ray_segment(config: tuple[CapModel, PoseConfig, DetectorConfig | None],
                raws: list[RawFrame], timing: CameraTiming | None = None,
                lookahead: RawFrame | None = None) -> list[replay.ReplayedFrame]:
    """A Ray task: one segment of a recording whose camera has ``timing`` through the pipeline
    (the worker keeps its FrameProcessor), with its ``lookahead`` frame (``replay.segments``)."""
    global _WORKER_KEY
    model, pose, detector = config
    key = settings_key(model, pose, detector)
    if key != _WORKER_KEY:
        replay._init_worker(model, pose, single_thread=True, detector=detector)
        _WORKER_KEY = key
    return replay._process_segment(raws, timing, lookahead)


class RayEngine:
    """Segments of any number of recordings on one Ray cluster, each recording's in order.

    Args:
        address: an existing cluster (``ray.init(address=...)``: ``auto``, ``HOST:6379``,
            ``ray://HOST:10001``), or None for an embedded single-machine Ray on loopback.
        num_cpus: CPUs of the embedded Ray (default: the machine's).
        retries: times a segment is re-run when its worker or node dies.
        model, pose: what every task processes with (shipped once through the object store).
        segment_fn: the task, ``fn((model, pose, detector), raws, timing[, lookahead]) ->
            processed frames`` (the look-ahead frame passed where there is one)
            (default: the pipeline; tests pass one that fails).
        detector: detector settings of every task (default ``DetectorConfig()``).
        start_timeout_s, segment_timeout_s: the waits' bounds (``START_TIMEOUT_S``,
            ``SEGMENT_TIMEOUT_S``).
        task_options: more Ray options of every task (tests: a resource no node has).

    Raises:
        ConfigError: ray missing, the cluster unreachable or not startable. WorkerError: no
            worker ran the first task within ``start_timeout_s``.
    """

    def __init__(self, model: CapModel, pose: PoseConfig, address: str | None = None,
                 num_cpus: int | None = None, retries: int = 2,
                 segment_fn: Callable[..., list[Any]] | None = None,
                 detector: DetectorConfig | None = None,
                 start_timeout_s: float = START_TIMEOUT_S,
                 segment_timeout_s: float = SEGMENT_TIMEOUT_S,
                 task_options: dict[str, Any] | None = None) -> None:
        # Never phone home (usage statistics), and keep an embedded Ray on loopback: Ray replaces
        # 127.0.0.1 by the machine's outward address unless it believes clusters are off.
        # The variable is read when ray is imported (here, and by the worker processes, which
        # inherit it); a ray imported earlier gets the constant set as well.
        os.environ.setdefault("RAY_USAGE_STATS_ENABLED", "0")
        loopback = address is None or _is_loopback_address(address)
        if loopback:
            os.environ["RAY_ENABLE_WINDOWS_OR_OSX_CLUSTER"] = "0"
        if address is not None:
            _check_reachable(address)
        try:
            import ray
        except ModuleNotFoundError as err:
            raise ConfigError("--ray needs ray: pip install ray==2.60.0 (pinned in requirements.txt; "
                              "the extra ficap_ros[ray])") from err

        self._ray = ray
        self._owned = not ray.is_initialized()
        if self._owned:
            if loopback:
                from ray._private import ray_constants

                ray_constants.ENABLE_RAY_CLUSTER = False
            try:
                if address is None:
                    ray.init(_node_ip_address="127.0.0.1", include_dashboard=False,
                             num_cpus=num_cpus or os.cpu_count() or 1, log_to_driver=False,
                             logging_level="ERROR")
                else:
                    ray.init(address=address, log_to_driver=False, logging_level="ERROR")
            except Exception as err:  # ray raises ConnectionError, RuntimeError, ValueError ...
                raise ConfigError(f"cannot start Ray{'' if address is None else f' at {address}'}: "
                               f"{str(err).splitlines()[0] if str(err) else type(err).__name__}") from err
            node_ip = ray.util.get_node_ip_address()
            if address is None and not node_ip.startswith("127."):
                ray.shutdown()
                raise ConfigError(f"the embedded Ray came up on {node_ip}, not loopback; refusing to run")
        self.cpus = max(int(ray.cluster_resources().get("CPU", 1)), 1)
        # Two segments per CPU in flight: workers never wait for the driver, and the driver holds
        # at most 2 x CPUs x 128 undecoded frames.
        self._slots = threading.BoundedSemaphore(2 * self.cpus)
        # Retries cover a worker or node that dies (max_retries); an exception raised by the
        # pipeline would only repeat, so it fails its recording at once.
        options = {"num_cpus": 1, **(task_options or {})}
        self._task = ray.remote(max_retries=int(retries), retry_exceptions=False, **options)(
            segment_fn or ray_segment)
        self.segment_timeout_s = float(segment_timeout_s)
        self._check_workers(ray.remote(max_retries=0, **options)(_probe), float(start_timeout_s))
        self._config = ray.put((model, pose, detector))
        #: What its tasks label with (``fingerprints.settings_key``).
        self.settings_key = settings_key(model, pose, detector)

    def _check_workers(self, probe: Any, timeout_s: float) -> None:
        """Run the first task; no answer within ``timeout_s`` is one line (and the embedded Ray
        is shut down), not a fleet that waits at 0 frames for ever."""
        ray = self._ray
        ref = probe.remote()
        try:
            ray.get(ref, timeout=timeout_s)
        except ray.exceptions.GetTimeoutError:
            ray.cancel(ref, force=True)
            self.close()
            raise WorkerError(f"no Ray worker started within {timeout_s:g} s ({self.cpus} CPUs); "
                              "the workers may lack memory or address space (see the Ray logs)"
                              ) from None
        except ray.exceptions.RayError as err:
            self.close()
            raise WorkerError(f"Ray's workers cannot run: {str(err).strip().splitlines()[-1]}"
                              ) from None

    def process(self, raws: Iterable[RawFrame], timing: CameraTiming | None = None) -> Iterator[Any]:
        """``replay``'s engine: processed frames of ``raws`` (of a camera with ``timing``; None:
        not known), in order (thread-safe)."""
        ray = self._ray
        it = replay.segments(raws, replay.two_sided_applies(timing))
        pending: deque[Any] = deque()
        done_reading = False
        try:
            while True:
                while not done_reading:
                    # Block for a slot only with nothing of ours in flight: a recording that
                    # holds finished segments must be free to collect them (no deadlock).
                    if not self._slots.acquire(blocking=not pending):
                        break
                    segment = next(it, None)
                    if segment is None:
                        self._slots.release()
                        done_reading = True
                        break
                    # The look-ahead only where there is one: a task takes (config, raws, timing).
                    raws_, lookahead = segment
                    extra = () if lookahead is None else (lookahead,)
                    pending.append(self._task.remote(self._config, raws_, timing, *extra))
                if not pending:
                    return
                ref = pending.popleft()
                try:
                    frames = ray.get(ref, timeout=self.segment_timeout_s)
                except ray.exceptions.GetTimeoutError:
                    ray.cancel(ref, force=True)
                    raise WorkerError(f"a segment did not come back from Ray within "
                                      f"{self.segment_timeout_s:g} s (workers stalled or lost)"
                                      ) from None
                finally:
                    self._slots.release()
                yield from frames
        finally:
            for ref in pending:
                ray.cancel(ref, force=True)
                self._slots.release()

    def close(self) -> None:
        if self._owned and self._ray.is_initialized():
            self._ray.shutdown()


def _host_port(address: str) -> tuple[str, int] | None:
    """(host, port) of ``HOST:PORT`` or ``ray://HOST:PORT``; None for ``auto`` and the like."""
    text = address.split("://", 1)[-1].rstrip("/")
    host, sep, port = text.rpartition(":")
    if not sep or not port.isdigit() or not host:
        return None
    return host.strip("[]"), int(port)


def _is_loopback_address(address: str) -> bool:
    hp = _host_port(address)
    return hp is not None and (hp[0] in ("localhost", "::1") or hp[0].startswith("127."))


def _check_reachable(address: str, timeout_s: float = 5.0) -> None:
    """Fail in one line when a cluster's port does not answer (ray.init retries for minutes)."""
    import socket

    hp = _host_port(address)
    if hp is None:
        return
    try:
        with socket.create_connection(hp, timeout=timeout_s):
            pass
    except OSError as err:
        raise ConfigError(f"no Ray cluster answers at {address}: {err.strerror or err}") from err
