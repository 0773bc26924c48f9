"""ficap_node over real rclpy on loopback: end-to-end latency and the highest sustained input rate.

The node (``python -m ficap_ros.ros.node``, default parameters, raw mono8 ``image`` + ``camera_info``)
runs in its own process; this process publishes rendered consecutive drive frames at a fixed rate
for ``--seconds`` per rate and records ``cap_pose``. Latency = arrival of the pose - publish time of
its image (matched by stamp), p50/p99. A rate is sustained when at least 99 % of the published
frames come back with a pose (the node's one-slot mailbox drops frames it cannot keep up with).
DDS stays on loopback (ROS_AUTOMATIC_DISCOVERY_RANGE=LOCALHOST; the caller's ROS_DOMAIN_ID, 70 unless set).

``--transports default,LARGE_DATA`` repeats the runs with Fast DDS's builtin-transports setting
(``FASTDDS_BUILTIN_TRANSPORTS``, Fast DDS >= 2.13): ``DEFAULT`` sends a sample bigger than the
shared-memory segment as UDP fragments, which best-effort delivery loses under load (a 1080p mono8
image is 2 MB); ``LARGE_DATA`` moves user data to shared memory / TCP; ``shm_large`` loads
``config/fastdds_shm_large.xml`` (shared memory only, 32 MB segments). ``compressed`` publishes
JPEG (quality 95) ``CompressedImage`` on ``image/compressed`` to a node started with
``image_transport:=compressed`` (default transports).

Writes docs/benchmarks/node.md.
"""

from __future__ import annotations

import argparse
import json
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
from _lib.cli import ROOT

QUICK = {"rates": "15,30", "seconds": 3.0, "resolutions": "540p", "transports": "default"}


def main(argv: list[str] | None = None) -> int:
    ap = cli.parser(__doc__, quick="540p, 15 and 30 Hz, 3 s each, default transports")
    ap.add_argument("--rates", default="10,30,60")
    ap.add_argument("--seconds", type=float, default=4.0)
    ap.add_argument("--resolutions", default="540p,1080p")
    ap.add_argument("--frames", type=int, default=90, help="distinct consecutive rendered frames, looped")
    ap.add_argument("--transports", default="default,shm_large,compressed",
                    help="comma-separated: default, compressed (JPEG on image/compressed), shm_large or a "
                         "FASTDDS_BUILTIN_TRANSPORTS value such as LARGE_DATA")
    ap.add_argument("--rows-json", type=Path, default=None, help=argparse.SUPPRESS)
    args = ap.parse_args(argv)
    if args.quick:
        for k, v in QUICK.items():
            setattr(args, k, v)
    cli.ros_environment()
    run = report.Run()
    transports = args.transports.split(",")
    if len(transports) == 1:
        rows = measure(args, transports[0])
    else:
        # Fast DDS reads its transport settings once per process (at the first participant), so
        # every transport runs in a process of its own, with the setting in place from the start.
        rows = []
        with tempfile.TemporaryDirectory() as tmp:
            for tr in transports:
                out = Path(tmp) / f"{tr}.json"
                cmd = [sys.executable, __file__, "--no-doc", "--transports", tr, "--rates", args.rates, "--seconds",
                       str(args.seconds), "--resolutions", args.resolutions, "--frames", str(args.frames),
                       "--rows-json", str(out)]
                subprocess.run(cmd, check=True)
                rows += json.loads(out.read_text())
    if args.rows_json is not None:
        args.rows_json.write_text(json.dumps(rows))
        return 0
    table = report.md_table(["res", "DDS transports", "input Hz", "frames sent", "frames with pose", "latency p50 ms",
                             "p99 ms", "sustained (>= 99 %)", "node peak RSS MB"], rows)
    body = (f"{table}\n\nThe publisher and the node share the machine's 2 cores with other jobs. 'shm_large': "
            "`config/fastdds_shm_large.xml` (shared memory only, 32 MB segments) for every participant: "
            "over Fast DDS's default transports a raw 1080p image (2 MB) travels as UDP fragments that "
            "best-effort delivery loses. 'compressed': JPEG q95 on `image/compressed` to a node "
            "started with `image_transport:=compressed`.")
    what = ("What it measures: `ficap_node` (default parameters, its own process) fed rendered "
            f"consecutive drive frames at fixed rates for {args.seconds:g} s each over loopback DDS: "
            "the share of frames that come back with a pose (the one-slot mailbox drops what the node "
            "cannot keep up with), the latency from publishing an image to receiving its `cap_pose`, "
            "and the node's peak memory; per transport setting, each in fresh processes.")
    report.write_section("node", what, report.how("bench_node.py", "540p, 2 rates, default transports"), body, run,
                         report.command(), args.quick, args.no_doc)
    return 0


def _peak_rss_mb(pid: int) -> str:
    """The process's peak resident memory (VmHWM), MB, from /proc; '-' where unavailable."""
    try:
        for line in Path(f"/proc/{pid}/status").read_text().splitlines():
            if line.startswith("VmHWM:"):
                return f"{int(line.split()[1]) / 1024:.0f}"
    except OSError:
        pass
    return "-"


def measure(args: argparse.Namespace, transport: str) -> list[list[object]]:
    """Rows of the table for one transport setting (set before this process makes a participant)."""
    os.environ.pop("FASTDDS_BUILTIN_TRANSPORTS", None)
    os.environ.pop("FASTRTPS_DEFAULT_PROFILES_FILE", None)
    if transport == "shm_large":
        os.environ["FASTRTPS_DEFAULT_PROFILES_FILE"] = str(ROOT / "config" / "fastdds_shm_large.xml")
    elif transport not in ("default", "compressed"):
        os.environ["FASTDDS_BUILTIN_TRANSPORTS"] = transport
    compressed = transport == "compressed"

    import rclpy
    from geometry_msgs.msg import PoseStamped
    from rclpy.executors import SingleThreadedExecutor
    from sensor_msgs.msg import CameraInfo, CompressedImage, Image
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

    rows: list[list[object]] = []
    env = dict(os.environ)
    for res in args.resolutions.split(","):
        scene = default_scene(res)
        model = nominal_model()
        drive = naturalistic_drive(600 + args.frames, fps=30.0, seed=0, scene=scene)[600:]
        images = [render(model, scene.camera, d.T_cam_cap, RenderConfig(), seed=d.index).image for d in drive]
        node_cmd = [sys.executable, "-m", "ficap_ros.ros.node"]
        if compressed:
            node_cmd += ["--ros-args", "-p", "image_transport:=compressed"]
        node_proc = subprocess.Popen(node_cmd, env=env,
                                     stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        rclpy.init()
        peer = rclpy.create_node("ficap_bench_peer")
        lock = threading.Lock()
        arrivals: dict[int, float] = {}

        def on_pose(msg: PoseStamped) -> None:
            t = time.perf_counter()
            with lock:
                arrivals[ros_msgs.stamp_to_ns(msg.header.stamp)] = t

        peer.create_subscription(PoseStamped, "cap_pose", on_pose, 100)
        pub_img = (peer.create_publisher(CompressedImage, "image/compressed", 5) if compressed
                   else peer.create_publisher(Image, "image", 5))
        jpegs = [cv2.imencode(".jpg", im, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes() for im in images]
        pub_info = peer.create_publisher(CameraInfo, "camera_info", 5)
        ex = SingleThreadedExecutor()
        ex.add_node(peer)
        spin = threading.Thread(target=ex.spin, daemon=True)
        spin.start()
        try:
            end = time.monotonic() + 60
            while pub_img.get_subscription_count() == 0 or peer.count_publishers("cap_pose") == 0:
                if time.monotonic() > end:
                    raise RuntimeError("ficap_node did not come up")
                time.sleep(0.05)
            stamp = 1_700_000_000_000_000_000
            msgs = []
            for img in images:
                msgs.append(img)

            def send(i: int, st: int) -> float:
                h = Header()
                h.stamp = messages.time(ros_msgs.RCLPY, st)
                h.frame_id = "camera"
                info = messages.camera_info(ros_msgs.RCLPY, h, scene.camera)
                if compressed:
                    im = CompressedImage(header=h, format="jpeg", data=jpegs[i % len(jpegs)])
                else:
                    im = messages.image(ros_msgs.RCLPY, h, msgs[i % len(msgs)], "mono8")
                pub_info.publish(info)
                t = time.perf_counter()
                pub_img.publish(im)
                return t

            # Warm-up: 20 frames lockstep-ish.
            for i in range(20):
                stamp += 33_333_333
                send(i, stamp)
                time.sleep(0.2)
            for rate in (float(r) for r in args.rates.split(",")):
                sent: dict[int, float] = {}
                period = 1.0 / rate
                n = int(args.seconds * rate)
                t_next = time.perf_counter()
                for i in range(n):
                    stamp += int(1e9 / rate)
                    sent[stamp] = send(i, stamp)
                    t_next += period
                    delay = t_next - time.perf_counter()
                    if delay > 0:
                        time.sleep(delay)
                time.sleep(1.0)
                with lock:
                    lat = np.array([(arrivals[s] - t) * 1e3 for s, t in sent.items() if s in arrivals])
                frac = len(lat) / max(n, 1)
                rows.append([res, transport, f"{rate:.0f}", n, f"{100 * frac:.1f} %",
                             f"{np.percentile(lat, 50):.1f}" if len(lat) else "-",
                             f"{np.percentile(lat, 99):.1f}" if len(lat) else "-",
                             "yes" if frac >= 0.99 else "no"])
                print(rows[-1], file=sys.stderr)
        finally:
            ex.shutdown()
            peer.destroy_node()
            rclpy.try_shutdown()
            peak_mb = _peak_rss_mb(node_proc.pid)
            for row in rows:
                if row[0] == res and row[1] == transport and len(row) == 8:
                    row.append(peak_mb)
            node_proc.terminate()
            node_proc.wait(timeout=20)
    return rows


if __name__ == "__main__":
    sys.exit(main())
