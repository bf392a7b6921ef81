"""The README's odometry-twist table: how well ``/rsvo/odom``'s twist follows the truth.

    python -m rsvo_ros.tools.twist_table OUT [--frames 90] [--jobs 2]

For each case a sharp bag is written (``rsvo_synth --frames N --motion M --severity S --seed
K``; the seeds of the README's motion-blur table, with its held-out ones) and replayed with the
defaults (window backend, RS model). From each replay's ``summary.json`` ``twist`` (see
``rsvo_ros.tools.replay.twist_summary``): the published angular velocity against the true
motion over the same interval and against the instantaneous row-0 rate, the linear velocity
against the interval's (after the trajectory's Sim(3) scale), the share within two standard
deviations of the published covariance, and beside them the window's keyframe velocities
(``keyframes.w_rel_error_median``, the RS model's own). Writes ``twist.md`` (per bag and per
group), ``twist.json`` and ``twist.png`` (the published turn rate of one vehicle and one
strongly shaken walk over time, with the truth at the stamps and over each interval) into OUT.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from rsvo_ros.sim.synth import SynthConfig
from rsvo_ros.tools.rate_table import run_cases
from rsvo_ros.tools.replay import ReplayConfig, ground_truth_of, replay
from rsvo_ros.tools.synth_bag import write_bag

# (motion, severity, seed): the motion-blur table's seeds (720-725 looked at there, 730-734
# written afterwards as its held-out check), sharp frames
CASES = [("vehicle", 1.0, 720), ("vehicle", 1.0, 721), ("vehicle", 1.0, 730),
         ("vehicle", 2.0, 731), ("handheld", 1.0, 720), ("handheld", 1.0, 721),
         ("handheld", 2.0, 734), ("walk", 1.0, 720), ("walk", 1.0, 721), ("walk", 1.0, 724),
         ("walk", 1.0, 733), ("walk", 2.0, 722), ("walk", 2.0, 723), ("walk", 2.0, 725),
         ("walk", 2.0, 730), ("walk", 2.0, 731), ("walk", 2.0, 732)]  # fmt: skip
PLOTTED = [("vehicle", 1.0, 720), ("walk", 2.0, 722)]


def run_case(out: Path, motion: str, severity: float, seed: int, frames: int) -> dict:
    """Write (or reuse) the case's bag, replay it and return its row."""
    bag = out / f"{motion}_sev{severity:g}_seed{seed}"
    if not (bag / "metadata.yaml").exists():
        write_bag(bag, SynthConfig(frames=frames, motion=motion, severity=severity, seed=seed),
                  overwrite=True, progress=False)  # fmt: skip
    s = replay(ReplayConfig(bag, out / f"{bag.name}__out", overwrite=True, progress=False))
    tw = s["twist"]
    row = {"case": bag.name, "motion": motion, "severity": severity, "seed": seed,
           "frames": tw["frames"], "known": tw["known"],
           "ate_m": s.get("accuracy", {}).get("ate_m", {}).get("rmse"),
           "keyframe_w_rel_error": s.get("keyframes", {}).get("w_rel_error_median")}
    for key in ("angular_interval_deg_s_median", "angular_error_vs_interval_deg_s_median",
                "linear_rel_error_vs_interval_median", "angular_true_deg_s_median",
                "angular_rel_error_median", "angular_within_2_sigma"):
        row[key] = tw.get(key)
    return row


def _group(row: dict) -> str:
    return f"{row['motion']} sev. {row['severity']:g}"


def _pct(x) -> str:
    return "-" if x is None else f"{100 * x:.0f} %"


def table(rows: list[dict]) -> str:
    lines = ["| bag | frames with a twist | turn rate over the interval (median) | angular error "
             "against it | linear error against the interval's (after Sim(3)) | against the "
             "instantaneous turn rate | within 2 sigma | RS keyframe velocity error |",
             "|---" * 8 + "|"]
    for r in rows:
        rate, err = r["angular_interval_deg_s_median"], r["angular_error_vs_interval_deg_s_median"]
        rel = None if rate is None or err is None or rate <= 0 else err / rate
        lines.append(
            f"| {r['motion']} sev. {r['severity']:g}, seed {r['seed']} | {r['known']} of "
            f"{r['frames']} | {'-' if rate is None else f'{rate:.1f} deg/s'} | "
            f"{'-' if err is None else f'{err:.1f} deg/s'} ({_pct(rel)}) | "
            f"{_pct(r['linear_rel_error_vs_interval_median'])} | "
            f"{_pct(r['angular_rel_error_median'])} | {_pct(r['angular_within_2_sigma'])} | "
            f"{_pct(r['keyframe_w_rel_error'])} |")
    return "\n".join(lines)


def summary(rows: list[dict]) -> str:
    """Per motion and severity: the range of each relative error over the bags."""
    out = []
    for g in dict.fromkeys(_group(r) for r in rows):
        rs = [r for r in rows if _group(r) == g]

        def span(values) -> str:
            v = [x for x in values if x is not None]
            return "-" if not v else f"{100 * min(v):.0f}-{100 * max(v):.0f} %"

        rel = [None if not r["angular_interval_deg_s_median"]
               or r["angular_error_vs_interval_deg_s_median"] is None
               else r["angular_error_vs_interval_deg_s_median"]
               / r["angular_interval_deg_s_median"] for r in rs]  # fmt: skip
        out.append(f"- {g} ({len(rs)} bags): angular {span(rel)} of the interval's turn rate, "
                   f"linear {span(r['linear_rel_error_vs_interval_median'] for r in rs)} of its "
                   f"speed; against the instantaneous rate "
                   f"{span(r['angular_rel_error_median'] for r in rs)}; within 2 sigma "
                   f"{span(r['angular_within_2_sigma'] for r in rs)}; RS keyframe velocities "
                   f"{span(r['keyframe_w_rel_error'] for r in rs)}")
    return "\n".join(out)


def rates(out_dir: Path) -> dict[str, np.ndarray]:
    """A replay's published angular velocities and the bag's true ones at the same stamps
    (``stamp_s``, ``published``, ``true`` (N, 3), ``interval`` (N, 3): the true poses'
    backward difference from the previous frame; rows without a twist left out)."""
    from rosbags.rosbag2 import Reader

    from rsvo_ros.odometry.twist import body_twist
    from rsvo_ros.ros import bagio
    from rsvo_ros.ros.convert import COVARIANCE_UNKNOWN

    def read(path: Path, topic: str) -> dict[int, object]:
        with Reader(path) as r:
            conns = [c for c in r.connections if c.topic == topic]
            return {t: bagio.deserialize(raw, c.msgtype) for c, t, raw in r.messages(conns)}

    summary_ = json.loads((out_dir / "summary.json").read_text())
    odom = read(out_dir / "odometry", "/rsvo/odom")
    gt = {s: ground_truth_of(m, bagio.ODOMETRY_TYPE)
          for s, m in read(Path(summary_["bag"]), "/ground_truth/odom").items()}
    stamps = sorted(gt)
    previous = dict(zip(stamps[1:], stamps[:-1], strict=True))
    rows = []
    for s, o in sorted(odom.items()):
        # no twist: 1e6 on the whole diagonal (a measured variance in map units may be large)
        if np.all(np.reshape(o.twist.covariance, (6, 6)).diagonal() == COVARIANCE_UNKNOWN) \
                or s not in previous:
            continue
        prev = previous[s]
        a = o.twist.twist.angular
        (T0, _), (T1, w_true) = gt[prev], gt[s]
        rows.append((s * 1e-9, [a.x, a.y, a.z], w_true,
                     body_twist(T0, T1, (s - prev) * 1e-9)[1]))
    return {"stamp_s": np.array([r[0] for r in rows]), "published": np.array([r[1] for r in rows]),
            "true": np.array([r[2] for r in rows]), "interval": np.array([r[3] for r in rows])}


def plot(path: Path, series: dict[str, dict[str, np.ndarray]]) -> None:
    """Per plotted case: the turn rate about the camera's y axis (pan) over time."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(len(series), 1, figsize=(10, 2.8 * len(series)), squeeze=False)
    for ax, (name, d) in zip(axes[:, 0], series.items(), strict=True):
        if len(d["stamp_s"]):
            t = d["stamp_s"] - d["stamp_s"][0]
            ax.plot(t, np.degrees(d["true"][:, 1]), "-", color="0.6", lw=1,
                    label="true, at the stamp (row 0)")
            ax.plot(t, np.degrees(d["interval"][:, 1]), "s", color="tab:green", ms=3,
                    label="true, mean over the interval")
            ax.plot(t, np.degrees(d["published"][:, 1]), "o", color="tab:blue", ms=3,
                    mfc="none", label="published twist")
            ax.legend(fontsize=7, loc="upper right")
        else:
            ax.text(0.5, 0.5, "no frame with a twist", ha="center", transform=ax.transAxes)
        ax.set_title(name, fontsize=9)
        ax.set_ylabel("turn rate about y (deg/s)")
        ax.grid(alpha=0.3)
    axes[-1, 0].set_xlabel("time (s)")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m rsvo_ros.tools.twist_table", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path)
    p.add_argument("--frames", type=int, default=90)
    p.add_argument("--jobs", type=int, default=1, help="cases replayed side by side (1)")
    args = p.parse_args(argv)
    if args.frames < 10 or args.jobs < 1:
        print("twist_table: --frames must be at least 10 and --jobs at least 1", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    rows = run_cases(run_case, [(args.out, *c, args.frames) for c in CASES], args.jobs,
                     lambda k, n, row: (
                         f"[twist_table] {row['case']}: {row['known']} of {row['frames']} "
                         f"frames with a twist, angular against the interval "
                         f"{row['angular_error_vs_interval_deg_s_median'] or float('nan'):.1f}"
                         f" deg/s"))
    (args.out / "twist.json").write_text(json.dumps(rows, indent=1))
    (args.out / "twist.md").write_text(table(rows) + "\n\n" + summary(rows) + "\n")
    series = {f"{m} severity {s:g}, seed {n}": rates(args.out / f"{m}_sev{s:g}_seed{n}__out")
              for m, s, n in PLOTTED}
    plot(args.out / "twist.png", series)
    print(summary(rows))
    print(f"wrote {args.out / 'twist.md'}, twist.json, twist.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
