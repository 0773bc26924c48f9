"""Soak: ficap_node for minutes at 30 Hz with a share of corrupt frames: memory, latency, losses.

The node (``python -m ficap_ros.ros.node``, ``image_transport:=compressed``, otherwise default
parameters) runs in its own process; this process publishes JPEG ``CompressedImage`` of rendered
consecutive drive frames (540p, quality 95, looped) with ``camera_info`` at ``--rate`` Hz for
``--minutes``. A ``--corrupt`` share of the frames, spread evenly by a seeded generator, is damaged, a third
each way: cut to 2/3 of its bytes, 2 kB of the scan zeroed (it decodes, and libjpeg prints
"Corrupt JPEG data" on stderr), or replaced by garbage. The node must answer every one (an ERROR
status, or a pose from what decoded) and go on. Every frame's ``status``
(DiagnosticArray) is recorded with its arrival time.

Per minute: frames sent, statuses received, good frames with a pose, damaged frames answered,
latency (status arrival - publish) p50 / p99, node resident memory (VmRSS from /proc, sampled
every 5 s). At the end: RSS growth from the first minute to the last, frames lost (sent without
any status: the one-slot mailbox drops frames it cannot keep up with), and how many lines the node
printed on stderr (libjpeg's per-frame messages go through its throttled logger).

DDS stays on loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST; the caller's ROS_DOMAIN_ID, 70 unless set).

Writes docs/benchmarks/soak.md.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tempfile
import threading
import time
from pathlib import Path

import cv2
import numpy as np

from _lib import cli, report


def _rss_mb(pid: int) -> float:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return float("nan")


def _damage(jpeg: bytes, kind: str, rng: np.random.Generator) -> bytes:
    if kind == "cut":  # a frame cut short
        return jpeg[: len(jpeg) * 2 // 3]
    if kind == "zeroed":  # 2 kB of the scan zeroed: decodes, with libjpeg's "Corrupt JPEG data"
        mid = len(jpeg) // 2
        return jpeg[:mid] + bytes(2000) + jpeg[mid + 2000:]
    return rng.integers(0, 256, 2000, dtype=np.uint8).tobytes()  # not a JPEG at all


def main(argv: list[str] | None = None) -> int:
    ap = cli.parser(__doc__, quick="1 minute (full: 10)")
    ap.add_argument("--minutes", type=float, default=None, help="minutes (default 10)")
    ap.add_argument("--rate", type=float, default=30.0)
    ap.add_argument("--corrupt", type=float, default=0.05)
    ap.add_argument("--resolution", default="540p")
    ap.add_argument("--frames", type=int, default=60, help="distinct rendered frames, looped")
    args = ap.parse_args(argv)
    args.minutes = args.minutes or (1.0 if args.quick else 10.0)
    cli.ros_environment()
    run = report.Run()

    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import CameraInfo, CompressedImage
    from std_msgs.msg import Header

    from ficap_ros.geometry.cap_model import nominal_model
    from ficap_ros.io import messages
    from ficap_ros.ros import msgs as ros_msgs
    from ficap_ros.tools.synth import (
        RenderConfig,
        default_scene,
        naturalistic_drive,
        render,
    )

    scene = default_scene(args.resolution)
    drive = naturalistic_drive(600 + args.frames, fps=args.rate, seed=0, scene=scene)[600:]
    model = nominal_model()
    jpegs = [cv2.imencode(".jpg", render(model, scene.camera, d.T_cam_cap, RenderConfig(),
                                         seed=d.index).image,
                          [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes() for d in drive]
    n_total = int(args.minutes * 60 * args.rate)
    rng = np.random.default_rng(13)
    damaged = rng.random(n_total) < args.corrupt
    kinds = rng.choice(["cut", "zeroed", "garbage"], n_total)

    stderr_file = tempfile.NamedTemporaryFile(prefix="ficap-soak-", suffix=".log", delete=False)
    node = subprocess.Popen([sys.executable, "-m", "ficap_ros.ros.node", "--ros-args", "-p",
                             "image_transport:=compressed"],
                            stdout=subprocess.DEVNULL, stderr=stderr_file)
    rclpy.init()
    peer = rclpy.create_node("ficap_soak_peer")
    lock = threading.Lock()
    status: dict[int, tuple[float, int, bool]] = {}  # stamp -> (arrival, level, has pose)

    def on_status(msg: DiagnosticArray) -> None:
        t = time.perf_counter()
        st = msg.status[0]
        with lock:
            status[ros_msgs.stamp_to_ns(msg.header.stamp)] = (t, int.from_bytes(st.level, "little")
                                                             if isinstance(st.level, bytes)
                                                             else int(st.level),
                                                             st.message == "pose")

    peer.create_subscription(DiagnosticArray, "status", on_status, 200)
    pub_img = peer.create_publisher(CompressedImage, "image/compressed", 5)
    pub_info = peer.create_publisher(CameraInfo, "camera_info", 5)
    ex = SingleThreadedExecutor()
    ex.add_node(peer)
    threading.Thread(target=ex.spin, daemon=True).start()
    rss: list[tuple[float, float]] = []
    sent: dict[int, tuple[float, bool]] = {}  # stamp -> (publish time, damaged)
    try:
        end = time.monotonic() + 60
        while pub_img.get_subscription_count() == 0 or peer.count_publishers("status") == 0:
            if time.monotonic() > end:
                raise RuntimeError("ficap_node did not come up")
            time.sleep(0.05)
        stamp = 1_700_000_000_000_000_000
        period = 1.0 / args.rate
        t0 = time.perf_counter()
        t_next = t0
        next_rss = t0
        for i in range(n_total):
            stamp += int(1e9 / args.rate)
            h = Header()
            h.stamp = messages.time(ros_msgs.RCLPY, stamp)
            h.frame_id = "camera"
            data = jpegs[i % len(jpegs)]
            if damaged[i]:
                data = _damage(data, str(kinds[i]), rng)
            pub_info.publish(messages.camera_info(ros_msgs.RCLPY, h, scene.camera))
            sent[stamp] = (time.perf_counter(), bool(damaged[i]))
            pub_img.publish(CompressedImage(header=h, format="jpeg", data=data))
            now = time.perf_counter()
            if now >= next_rss:
                rss.append((now - t0, _rss_mb(node.pid)))
                next_rss += 5.0
            t_next += period
            delay = t_next - time.perf_counter()
            if delay > 0:
                time.sleep(delay)
        time.sleep(2.0)
        rss.append((time.perf_counter() - t0, _rss_mb(node.pid)))
    finally:
        ex.shutdown()
        peer.destroy_node()
        rclpy.try_shutdown()
        node.terminate()
        node.wait(timeout=30)
        stderr_file.close()

    stderr_lines = Path(stderr_file.name).read_text(errors="replace").splitlines()
    if os.environ.get("FICAP_SOAK_SHOW_STDERR"):
        print("\n".join(stderr_lines), file=sys.stderr)
    os.unlink(stderr_file.name)
    rows = []
    minutes = int(np.ceil(args.minutes))
    stamps = sorted(sent)
    first_pub = sent[stamps[0]][0]
    lost_total = 0
    for m in range(minutes):
        window = [s for s in stamps if m * 60 <= sent[s][0] - first_pub < (m + 1) * 60]
        if not window:
            continue
        with lock:
            got = [s for s in window if s in status]
            lat = np.array([(status[s][0] - sent[s][0]) * 1e3 for s in got])
            good_pose = sum(1 for s in got if not sent[s][1] and status[s][2])
            bad_answered = sum(1 for s in got if sent[s][1])
        good_sent = sum(1 for s in window if not sent[s][1])
        lost = len(window) - len(got)
        lost_total += lost
        mem = [r for t, r in rss if m * 60 <= t < (m + 1) * 60]
        rows.append([m + 1, len(window), len(got), f"{good_pose}/{good_sent}",
                     f"{bad_answered}/{len(window) - good_sent}",
                     f"{np.percentile(lat, 50):.1f}" if lat.size else "-",
                     f"{np.percentile(lat, 99):.1f}" if lat.size else "-",
                     f"{max(mem):.0f}" if mem else "-"])
        print(rows[-1], file=sys.stderr)
    first_min = [r for t, r in rss if t < 60]
    last_min = [r for t, r in rss if t >= rss[-1][0] - 60]
    growth = float(np.median(last_min) - np.median(first_min)) if first_min and last_min else 0.0
    libjpeg_lines = sum(1 for ln in stderr_lines if "Corrupt JPEG" in ln or "Premature end" in ln)
    decode_lines = sum(1 for ln in stderr_lines if "cannot decode" in ln)
    table = report.md_table(["minute", "sent", "statuses", "good with pose", "damaged answered",
                             "latency p50 ms", "p99 ms", "node RSS MB"], rows)
    body = "\n".join([
        table, "",
        f"Node RSS {np.median(first_min):.0f} MB (median of minute 1) -> "
        f"{np.median(last_min):.0f} MB (last minute): growth {growth:+.1f} MB over "
        f"{args.minutes:g} min. Frames lost (sent, no status): {lost_total} of {len(stamps)} "
        f"({100 * lost_total / max(len(stamps), 1):.2f} %). Node stderr for "
        f"{int(damaged.sum())} damaged frames ({int((damaged & (kinds == 'zeroed')).sum())} with "
        f"libjpeg warnings): {len(stderr_lines)} lines in all, {libjpeg_lines} of libjpeg's "
        f"(through the throttled logger), {decode_lines} throttled 'cannot decode' warnings."])
    what = (f"What it measures: `ficap_node` (`image_transport:=compressed`, otherwise defaults) fed "
            f"{args.resolution} JPEG (q95) at {args.rate:.0f} Hz for {args.minutes:g} min over loopback "
            f"DDS, {100 * args.corrupt:.0f} % of the frames damaged (a third each: cut to 2/3 of their "
            "bytes, 2 kB of the scan zeroed, garbage). Per minute: frames sent, statuses received, "
            "good frames with a pose, damaged frames answered (ERROR or a pose from the decoded "
            "part), latency from publish to status, the node's peak RSS of 5 s samples.")
    report.write_section("soak", what, report.how("bench_soak.py", "1 minute"), body, run, report.command(),
                         args.quick, args.no_doc)
    return 0


if __name__ == "__main__":
    sys.exit(main())
