"""Measure a running rsvo_node: end-to-end latency and the input rate it sustains.

    python -m rsvo_ros.ros.latency --rate 15 --resolution 1280x720 --frames 90

Publishes rendered rolling-shutter frames (and camera info) stamped with the wall clock at the
given rate, subscribes to ``/rsvo/odom`` and ``/diagnostics`` and reports, per run: frames sent,
odometry received (the node drops frames it cannot keep up with and counts them), the latency
from the image stamp to the odometry's arrival (median, p95), the node's own stage times from its
diagnostics (tracking per frame, mapping per keyframe, publishing per frame, medians) and its
CPU use (% of one core, from /proc; the node is found by name or ``--node-pid``), and the
node's frame counters over the run (received, processed, dropped, held, skipped: why frames
got no odometry), which frames got none (``missing_frames``) and which were the slowest
twentieth (``tail_frames``, ``[frame, delay_ms]``: the delay p95's stretch), and the live ATE
against the frames' ground truth (``ate_m``; ``--seed`` picks the rendered sequence, a row's
``seed``). Start the node first, e.g. ``rsvo_node --ros-args -p line_delay:=5e-5``.
``--bag DIR`` also writes the frames as sent (their wall-clock stamps, camera info, ground
truth and the rendering's line delay) as a rosbag2, after the run (one rate): where the node
dropped no frame, ``rsvo_replay DIR --mapping-lag 0.05`` (the node's lag) gives its poses.

The node must run with the line delay the frames are rendered with, which depends on the rate
with ``--motion-at-rate`` (the readout is at most one frame interval: 33 ms at 30 Hz, 36 ms at
15 Hz): ``--print-line-delay`` prints it for one ``--rate`` (as the ``--bag`` records it) and
exits, and each row records it beside the node's own (``line_delay_rendered_s``,
``line_delay_node``; a warning where they differ).

``--summary RESULT.json ...`` prints the results of earlier runs as the README's table, each
row against issue 14's targets (``launch_scripts/latency_table.sh`` runs and summarises).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import time

import numpy as np

from rsvo_ros.sim.synth import SynthConfig, resolution_arg


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m rsvo_ros.ros.latency", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--rate", type=float, nargs="+", default=[15.0], help="input rates (Hz)")
    p.add_argument("--resolution", type=resolution_arg, default="1280x720", metavar="WxH",
                   help="image size (default 1280x720)")
    p.add_argument("--frames", type=int, default=60, help="frames per rate")
    p.add_argument("--motion", default="vehicle")
    p.add_argument("--motion-at-rate", action="store_true",
                   help="sample the motion at each input rate, as a camera at that rate sees it "
                        "(at 15 Hz twice the motion per frame of 30 Hz); default: the motion's "
                        "own 30 Hz frames, played at the input rate (the README's tables "
                        "before the thirty-third session)")
    p.add_argument("--seed", type=int, default=0,
                   help="the rendered sequence's seed (rsvo_synth's; default 0, the one every "
                        "table so far used)")
    p.add_argument("--json", default=None, help="also write the results here")
    p.add_argument("--bag", default=None, metavar="DIR",
                   help="also write the frames as sent (their stamps) as a rosbag2 here, "
                        "after the run: the replay of what the node got (one --rate)")
    p.add_argument("--print-line-delay", action="store_true",
                   help="print the line delay (s per row) of the frames this probe renders for "
                        "its one --rate, --resolution, --motion and --motion-at-rate (what the "
                        "node must be given: python -m rsvo_ros.ros.latency --rate 30 "
                        "--motion-at-rate --print-line-delay) and exit")
    p.add_argument("--node-pid", type=int, default=None,
                   help="the node's process id (default: the process running rsvo_node)")
    p.add_argument("--wait", type=float, default=120.0, metavar="S",
                   help="seconds to wait for the node to subscribe to the images and advertise "
                        "its odometry before giving up (default 120: a node's first start "
                        "after an install compiles its solver, about a minute)")
    p.add_argument("--summary", nargs="+", metavar="RESULT_JSON", default=None,
                   help="print earlier runs' --json files as a markdown table and exit")
    args = p.parse_args(argv)
    if args.summary:
        rows = []
        for path in args.summary:
            with open(path) as f:
                rows.extend(json.load(f))
        print(summary_table(rows))
        return 0
    if args.seed < 0:
        p.error(f"--seed must be a non-negative integer, got {args.seed}")
    if not args.wait > 0:
        p.error(f"--wait must be a positive number of seconds, got {args.wait}")
    if args.bag is not None and (len(args.rate) != 1 or os.path.exists(args.bag)):
        p.error(f"--bag takes one --rate and a path that does not exist, got {args.bag} "
                f"with {len(args.rate)} rates")
    w, h = args.resolution
    if args.print_line_delay:
        if len(args.rate) != 1:
            p.error(f"--print-line-delay takes one --rate, got {len(args.rate)}")
        rate = args.rate[0] if args.motion_at_rate else None
        print(line_delay_text(render_config(2, args.motion, w, h, rate, args.seed).tau))
        return 0

    import rclpy
    from diagnostic_msgs.msg import DiagnosticArray
    from nav_msgs.msg import Odometry
    from rclpy.qos import QoSProfile, ReliabilityPolicy
    from sensor_msgs.msg import CameraInfo, Image

    from rsvo_ros.sim.synth import SequenceRenderer

    def render(rate: float | None):
        """The frames' bytes and ground-truth poses ``(R_world_cam, p_world_cam)``, the motion
        sampled at ``rate`` (None: its own rate), the camera matrix, the rate the motion was
        sampled at and the line delay; rendered before publishing, which must keep time."""
        cfg = render_config(args.frames, args.motion, w, h, rate, args.seed)
        renderer = SequenceRenderer(cfg)
        frames = list(renderer)
        poses = [(f.R_world_cam.copy(), f.p_world_cam.copy()) for f in frames]
        return [f.image.tobytes() for f in frames], poses, renderer.K, cfg.rate_hz, cfg.tau

    rendered = None if args.motion_at_rate else render(None)
    rclpy.init()
    node = rclpy.create_node("rsvo_latency")
    qos = QoSProfile(depth=10, reliability=ReliabilityPolicy.RELIABLE)
    pub_img = node.create_publisher(Image, "/camera/image_raw", qos)
    pub_info = node.create_publisher(CameraInfo, "/camera/camera_info", qos)
    got: dict[int, float] = {}
    positions: dict[int, np.ndarray] = {}

    def on_odom(m):
        stamp = m.header.stamp.sec * 10**9 + m.header.stamp.nanosec
        got.setdefault(stamp, time.time())
        p = m.pose.pose.position
        positions[stamp] = np.array([p.x, p.y, p.z])

    node.create_subscription(Odometry, "/rsvo/odom", on_odom, qos)
    diag: dict[str, str] = {}

    def on_diag(m):
        for st in m.status:
            if st.name.startswith("rsvo_node"):
                diag.clear()
                diag.update({kv.key: kv.value for kv in st.values})

    node.create_subscription(DiagnosticArray, "/diagnostics", on_diag, 10)
    pid = args.node_pid or _find_pid("rsvo_node")
    def node_ready() -> bool:
        return pub_img.get_subscription_count() > 0 and node.count_publishers("/rsvo/odom") > 0

    t_end = time.monotonic() + args.wait
    while time.monotonic() < t_end and not node_ready():
        rclpy.spin_once(node, timeout_sec=0.05)
    if not node_ready():
        # frames sent to nobody would be counted as frames the node missed
        print(f"no node subscribed to /camera/image_raw and advertised /rsvo/odom within "
              f"{args.wait:g} s (ROS_DOMAIN_ID {os.environ.get('ROS_DOMAIN_ID', 'unset')}): "
              f"start rsvo_node first, in the same ROS domain", file=sys.stderr)
        node.destroy_node()
        rclpy.try_shutdown()
        return 2
    t_settle = time.monotonic() + 2.0
    while time.monotonic() < t_settle:
        rclpy.spin_once(node, timeout_sec=0.05)
    results = []
    for rate in args.rate:
        images, poses, K, motion_rate, tau = rendered or render(rate)
        got.clear()
        positions.clear()
        sent = []
        counts0 = _frame_counts(diag)
        cpu0 = _cpu_seconds(pid)
        t0 = time.monotonic()
        for k, data in enumerate(images):
            due = t0 + k / rate
            while time.monotonic() < due:
                rclpy.spin_once(node, timeout_sec=max(0.0, min(0.005, due - time.monotonic())))
            ns = time.time_ns()
            info = CameraInfo()
            info.header.stamp.sec, info.header.stamp.nanosec = ns // 10**9, ns % 10**9
            info.width, info.height = w, h
            info.k = [float(x) for x in K.ravel()]
            img = Image()
            img.header = info.header
            img.height, img.width, img.encoding, img.step, img.data = h, w, "mono8", w, data
            pub_info.publish(info)
            pub_img.publish(img)
            sent.append(ns)
        t_sent = time.monotonic()
        cpu1 = _cpu_seconds(pid)
        t_drain = time.monotonic() + 5.0
        while time.monotonic() < t_drain:
            rclpy.spin_once(node, timeout_sec=0.05)
        # each frame with odometry: from its stamp to the odometry's arrival (ms)
        delays = {k: (got[s] - s / 1e9) * 1e3 for k, s in enumerate(sent) if s in got}
        lat = np.array(list(delays.values()))
        row = {"rate_hz": rate, "resolution": f"{w}x{h}", "sent": len(sent),
               "odometry": len(lat),
               "latency_ms_median": float(np.median(lat)) if len(lat) else None,
               "latency_ms_p95": float(np.percentile(lat, 95)) if len(lat) else None,
               "node_cpu_percent": None if cpu0 is None or cpu1 is None
               else 100.0 * (cpu1 - cpu0) / (t_sent - t0),
               "tracking_ms_median": diag.get("tracking_time_ms_median"),
               "mapping_ms_median": diag.get("mapping_time_ms_median"),
               "publishing_ms_median": diag.get("publishing_time_ms_median"),
               "processing_ms_median": diag.get("processing_time_ms_median"),
               # the node's slow frames (its last 100), beside the delay's p95
               "processing_ms_p95": diag.get("processing_time_ms_p95"),
               "tracking_ms_p95": diag.get("tracking_time_ms_p95"),
               # how old images were on arrival at the node (its last 100): this probe's
               # message construction, DDS, and the node's executor
               "image_delay_ms_median": diag.get("image_delay_ms_median"),
               "dds_profile": dds_profile_name(),
               # the node's tracking_decimation (its diagnostics; 1: full resolution)
               "tracking_decimation": int(diag.get("tracking_decimation", 1)),
               # fixed, or auto (then tracking_decimation is where it ended)
               "tracking_decimation_mode": diag.get("tracking_decimation_mode", "fixed"),
               # which frames got no odometry (dropped while busy, held, lost): a start-up
               # phase shows as the first indices
               "missing_frames": [k for k, s in enumerate(sent) if s not in got],
               # the frames whose delay makes the p95: where the slow stretch is
               "tail_frames": tail_frames(delays),
               # the node's own counts over this run (diagnostics): why frames are missing
               "node_frames": {k: n - counts0.get(k, 0) for k, n in _frame_counts(diag).items()},
               # the motion per frame: sampled at this rate, or the motion's own frames
               "motion_rate_hz": motion_rate, "seed": args.seed,
               # the line delay the frames were rendered with (as --bag records it) and the
               # node's (its diagnostics): a node told another one runs a miscalibrated camera
               "line_delay_rendered_s": float(line_delay_text(tau)),
               "line_delay_node": diag.get("line_delay")}
        if not line_delay_matches(row["line_delay_node"], tau):
            print(f"warning: the node runs with line_delay {row['line_delay_node']}, the "
                  f"frames were rendered with {line_delay_text(tau)} (python -m "
                  f"rsvo_ros.ros.latency --rate {rate:g} ... --print-line-delay): its "
                  f"accuracy is not a calibrated camera's", file=sys.stderr)
        row.update(live_ate({s: poses[k][1] for k, s in enumerate(sent)}, positions))
        results.append(row)
        print(json.dumps(row))
        if args.bag is not None:
            write_sent_bag(args.bag, sent, images, K, w, h, poses, tau)
            print(f"wrote the frames as sent to {args.bag}", file=sys.stderr)
    if args.json:
        with open(args.json, "w") as f:
            json.dump(results, f, indent=1)
    node.destroy_node()
    rclpy.try_shutdown()
    return 0


def render_config(frames: int, motion: str, width: int, height: int, rate: float | None,
                  seed: int) -> SynthConfig:
    """The probe's rendered sequence: ``motion`` sampled at ``rate`` (None: at its own rate);
    its ``tau`` is the line delay the frames have (the readout capped at one frame interval)."""
    return SynthConfig(frames=frames, motion=motion, width=width, height=height,
                       frame_rate=rate, seed=seed)


def line_delay_text(line_delay: float) -> str:
    """A line delay as the probe prints it and its ``--bag`` records it (12 significant
    digits): a node given this text and the bag's replay run with the same number."""
    return format(float(line_delay), ".12g")


def line_delay_matches(node_text: str | None, rendered: float) -> bool:
    """Whether the node's line delay (its diagnostics' text; None: not reported yet, taken
    as matching) is the rendered one to a part in 1e9."""
    if node_text is None:
        return True
    try:
        node = float(node_text)
    except ValueError:
        return False
    return abs(node - rendered) <= 1e-9 * max(abs(rendered), 1e-300)


def write_sent_bag(path, stamps_ns: list[int], images: list[bytes], K: np.ndarray,
                   width: int, height: int, poses: list[tuple[np.ndarray, np.ndarray]],
                   line_delay: float) -> None:
    """The frames as the probe sent them, as a rosbag2 (sqlite3) at ``path``: ``mono8``
    images (``images``, row-major bytes) and camera info stamped ``stamps_ns``, the ground
    truth (``poses``: ``(R_world_cam, p_world_cam)`` per frame) and the rendering's line
    delay, in the layout ``rsvo_synth`` writes."""
    from rsvo_ros.ros import bagio

    if not len(stamps_ns) == len(images) == len(poses):
        raise ValueError(f"{len(stamps_ns)} stamps, {len(images)} images and {len(poses)} "
                         f"poses: one of each per frame")
    ts = bagio.typestore()
    with bagio.open_writer(path, "sqlite3") as writer:
        writer.set_custom_data(bagio.LINE_DELAY_KEY, line_delay_text(line_delay))
        connections = bagio.frame_connections(writer, ts)
        for stamp, data, (R, p) in zip(stamps_ns, images, poses, strict=True):
            image = np.frombuffer(data, np.uint8).reshape(height, width)
            bagio.write_frame(writer, connections, stamp, bagio.image_msg(stamp, image), K, width,
                              height, R, p)


def live_ate(truth: dict[int, np.ndarray], odometry: dict[int, np.ndarray]) -> dict:
    """``{"ate_m": ...}``: the RMSE of the positions (3,) of the odometry received after a
    Sim(3) alignment to the ground-truth positions of the frames sent (both by stamp; evo's
    Umeyama alignment, so the replay's ATE), or ``{"ate_m": None, "ate_error": why}`` where it
    cannot be computed (too few or degenerate poses)."""
    from evo.core.geometry import umeyama_alignment

    stamps = sorted(s for s in odometry if s in truth)
    try:
        if len(stamps) < 3:
            raise ValueError(f"{len(stamps)} poses with ground truth")
        est = np.array([odometry[s] for s in stamps]).T
        ref = np.array([truth[s] for s in stamps]).T
        R, t, c = umeyama_alignment(est, ref, with_scale=True)
        err = c * R @ est + t[:, None] - ref
        ate = float(np.sqrt(np.mean(np.sum(err**2, axis=0))))
        if not np.isfinite(ate):
            raise ValueError("not finite")
        return {"ate_m": ate}
    except Exception as exc:  # noqa: BLE001 - any alignment failure is reported, not raised
        return {"ate_m": None, "ate_error": f"{type(exc).__name__}: {exc}"}


def tail_frames(delays_ms: dict[int, float], share: float = 0.05) -> list[list[float]]:
    """``[[frame, delay_ms], ...]`` of the slowest ``share`` of the frames with odometry (at
    least one; by frame index; delays rounded to 0.1 ms): the frames a delay p95 is made of,
    so a run says where its slow stretch is (the walk's look-around: frames 128-170)."""
    if not delays_ms:
        return []
    n = max(1, int(np.ceil(share * len(delays_ms))))
    slowest = sorted(delays_ms, key=lambda k: (-delays_ms[k], k))[:n]
    return [[k, round(float(delays_ms[k]), 1)] for k in sorted(slowest)]


# issue 14's targets: (resolution, rate) -> (share of frames with odometry, delay p95 ms)
TARGETS = {("1280x720", 15.0): (0.98, 60.0), ("1280x720", 30.0): (0.90, 80.0),
           ("640x480", 30.0): (0.98, None)}
NODE_CPU_TARGET = {("1280x720", 15.0): 150.0}  # % of one core


def _decimation(row: dict) -> str:
    """A row's tracking decimation: the factor, or 'auto (ended at N)'."""
    d = row.get("tracking_decimation", 1)
    return f"auto (ended at {d})" if row.get("tracking_decimation_mode") == "auto" else str(d)


def _seed(row: dict) -> str:
    """The sequence's seed where it is not the default 0 (rows from before the field: 0)."""
    return f" (seed {row['seed']})" if row.get("seed", 0) else ""


def summary_table(rows: list[dict]) -> str:
    """The probe's result rows as a markdown table, sorted by resolution and rate, with each
    issue-14 target the row has and whether it was met."""
    def key(r):
        w, h = (int(x) for x in r["resolution"].split("x"))
        return (w * h, r["rate_hz"], r.get("dds_profile", "default"),
                r.get("tracking_decimation_mode", "fixed") == "auto",
                r.get("tracking_decimation", 1), r.get("seed", 0))

    def ms(x):
        return "-" if x is None else f"{x:.0f}"

    lines = ["| resolution | rate | Fast DDS profile | tracking decimation | frames with odometry "
             "| delay median / p95 | image arrival (median) | node CPU | tracking / mapping / "
             "publishing (median) | dropped / held | motion per frame | ATE | target |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for r in sorted(rows, key=key):
        frames = r["odometry"] / max(r["sent"], 1)
        target = TARGETS.get((r["resolution"], float(r["rate_hz"])))
        cpu_target = NODE_CPU_TARGET.get((r["resolution"], float(r["rate_hz"])))
        verdict = []
        if target is not None:
            share, p95 = target
            ok = frames >= share
            verdict.append(f">= {100 * share:.0f} % {'met' if ok else 'not met'}")
            if p95 is not None:
                ok = r["latency_ms_p95"] is not None and r["latency_ms_p95"] <= p95
                verdict.append(f"p95 <= {p95:.0f} ms {'met' if ok else 'not met'}")
        cpu = r.get("node_cpu_percent")
        if cpu_target is not None:
            ok = cpu is not None and cpu <= cpu_target
            verdict.append(f"CPU <= {cpu_target / 100:.1f} cores {'met' if ok else 'not met'}")
        nf = r.get("node_frames", {})
        lines.append(
            f"| {r['resolution']} | {r['rate_hz']:g} Hz | {r.get('dds_profile', 'default')} | "
            f"{_decimation(r)} | "
            f"{r['odometry']} / {r['sent']} ({100 * frames:.1f} %) | "
            f"{ms(r['latency_ms_median'])} / {ms(r['latency_ms_p95'])} ms | "
            f"{r.get('image_delay_ms_median') or '-'} ms | {ms(cpu)} % | "
            f"{r.get('tracking_ms_median')} / "
            f"{r.get('mapping_ms_median')} / {r.get('publishing_ms_median')} ms | "
            f"{nf.get('dropped', '-')} / {nf.get('held', '-')} | "
            f"{r.get('motion_rate_hz', 30.0):g} Hz{_seed(r)} | "
            f"{'-' if r.get('ate_m') is None else format(r['ate_m'], '.3f') + ' m'} | "
            f"{'; '.join(verdict) or '-'} |")
    return "\n".join(lines)


def dds_profile_name() -> str:
    """Which Fast DDS profile this process runs with: ``default``, ``large_images`` (the
    shipped one, :mod:`rsvo_ros.ros.dds`) or the path of another profile file."""
    from rsvo_ros.ros.dds import LARGE_IMAGES_PROFILE, PROFILE_ENV

    path = os.environ.get(PROFILE_ENV)
    if not path:
        return "default"
    try:
        return "large_images" if os.path.samefile(path, LARGE_IMAGES_PROFILE) else path
    except OSError:
        return path


FRAME_COUNTS = ("received", "processed", "dropped", "held", "skipped", "bad", "time_resets")


def _frame_counts(diag: dict[str, str]) -> dict[str, int]:
    """The node's frame counters from its last diagnostics (empty before any)."""
    return {k: int(diag[k]) for k in FRAME_COUNTS if diag.get(k, "").isdigit()}


def _find_pid(name: str) -> int | None:
    """The first process (not this one) whose command line names ``name``."""
    from pathlib import Path

    for d in Path("/proc").iterdir():
        if not d.name.isdigit() or int(d.name) == os.getpid():
            continue
        try:
            cmd = (d / "cmdline").read_bytes().replace(b"\0", b" ").decode(errors="replace")
        except OSError:
            continue
        if name in cmd and "latency" not in cmd:
            return int(d.name)
    return None


def _cpu_seconds(pid: int | None) -> float | None:
    """User + system CPU seconds of a process (all its threads), None if unknown."""
    if pid is None:
        return None
    try:
        fields = open(f"/proc/{pid}/stat").read().rsplit(")", 1)[1].split()
    except OSError:
        return None
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


if __name__ == "__main__":
    sys.exit(main())
