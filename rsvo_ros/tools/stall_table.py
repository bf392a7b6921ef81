"""The README's stalled-camera table: odometry across frames that never came.

    python -m rsvo_ros.tools.stall_table [--frames 210] [--jobs 2] [--json OUT.json]

A camera, a driver or the node itself can stall: for a fraction of a second no frame comes,
then the stream goes on. For each case a sequence is rendered (``rsvo_synth``'s motions, the
true line delay given), the frames of each gap ``(first, count)`` are left out, and the rest go
through :class:`~rsvo_ros.odometry.pipeline.OdometryPipeline` (window backend, the replay's
defaults) twice: with the stall check (``WindowOptions.stall_intervals``, the node's
``stall_frames``, at its default) and without it (0, the pipeline before the fiftieth
session); once more with no frame left out. Each row: the ATE (Sim(3)) of the three runs, and
what the first frame after the gap was (status, reason) with and without the check. The
cases "looked at" are those the check was chosen on; the "held out" ones were run once, after
it was chosen (README, "A stalled camera").
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys

import numpy as np

from rsvo_ros.odometry.pipeline import OdometryPipeline, PipelineOptions
from rsvo_ros.odometry.window import STALL_INTERVALS
from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig
from rsvo_ros.tools.line_delay_table import case_name
from rsvo_ros.tools.rate_table import run_cases
from rsvo_ros.tools.replay import accuracy

CASES = [  # (group, motion, severity, seed, line delay s/row, gaps (first frame, frames))
    *[("looked at", m, sev, seed, ld, ((80, 16), (120, 9)))
      for m, sev, seed, ld in (("vehicle", 1.0, 200, 5e-5), ("vehicle", 2.0, 500, 6e-5),
                               ("vehicle", 1.0, 0, 5e-5), ("vehicle", 1.0, 300, 7e-5),
                               ("vehicle", 2.0, 301, 1e-4), ("vehicle", 2.0, 201, 2e-5),
                               ("walk", 1.0, 200, 5e-5), ("walk", 2.0, 202, 5e-5),
                               ("handheld", 1.0, 200, 1e-4), ("handheld", 1.0, 300, 5e-5))],
    *[("held out", m, sev, seed, ld, ((100, 6), (100, 12), (100, 20)))
      for m, sev, seed, ld in (("vehicle", 1.0, 700, 5e-5), ("vehicle", 1.0, 701, 3e-5),
                               ("vehicle", 2.0, 702, 8e-5), ("vehicle", 2.0, 703, 4e-5),
                               ("walk", 1.0, 700, 6e-5), ("walk", 2.0, 701, 4e-5),
                               ("handheld", 1.0, 700, 7e-5), ("handheld", 2.0, 701, 5e-5))],
]
SAME = 1e-9  # m: ATEs this close are the same run


def _run(frames, K: np.ndarray, line_delay: float, stall_intervals: float,
         after: int | None) -> tuple[float, tuple[str, str] | None]:  # fmt: skip
    """The frames through a pipeline (the true line delay, fixed): the ATE and the status and
    reason of frame ``after`` (its index)."""
    options = PipelineOptions(line_delay_auto=False, line_delay_auto_refine_frames=0)
    options.window.stall_intervals = stall_intervals
    pipe = OdometryPipeline(K, None, line_delay, options)
    truth, est, first = {}, {}, None
    try:
        for f in frames:
            res = pipe.process(round(f.stamp * 1e9), f.image)
            truth[res.stamp_ns] = f.pose()
            if res.T_world_cam is not None:
                est[res.stamp_ns] = res.T_world_cam
            if f.index == after:
                first = (res.status, res.reason)
    finally:
        pipe.close()
    ate = accuracy({s: truth[s] for s in est}, est)["ate_m"]["rmse"] if len(est) >= 3 else None
    return ate, first


def run_case(group: str, motion: str, severity: float, seed: int, line_delay: float,
             gaps: tuple[tuple[int, int], ...], frames: int) -> list[dict]:  # fmt: skip
    """One sequence rendered once, run without a gap and, for each gap, with and without the
    stall check: a row per gap."""
    renderer = SequenceRenderer(SynthConfig(frames=frames, motion=motion, severity=severity,
                                            seed=seed, line_delay=line_delay))  # fmt: skip
    rendered = list(renderer)
    interval = rendered[1].stamp - rendered[0].stamp
    no_gap, _ = _run(rendered, renderer.K, line_delay, STALL_INTERVALS, None)
    rows = []
    for first, count in gaps:
        kept = [f for f in rendered if not first <= f.index < first + count]
        on, after_on = _run(kept, renderer.K, line_delay, STALL_INTERVALS, first + count)
        off, after_off = _run(kept, renderer.K, line_delay, 0.0, first + count)
        rows.append({"group": group, "case": case_name(motion, severity, seed, line_delay),
                     "motion": motion, "gap_first": first, "gap_frames": count,
                     "gap_s": (count + 1) * interval, "ate_no_gap_m": no_gap,
                     "ate_off_m": off, "ate_on_m": on,
                     "after_off": after_off, "after_on": after_on})
    return rows


def verdict(row: dict) -> str:
    """``better``, ``worse`` or ``same`` (the check's ATE against the run without it)."""
    on, off = row["ate_on_m"], row["ate_off_m"]
    if on is None or off is None:
        return "worse" if on is None and off is not None else "same"
    return "same" if abs(on - off) <= SAME else ("better" if on < off else "worse")


def _m(x: float | None) -> str:
    return "-" if x is None else f"{x:.3f}"


def table(rows: list[dict]) -> str:
    lines = ["| group | case | gap | ATE, no gap | ATE, check off | ATE, check on | the frame "
             "after it, check on |", "|---|---|---|---|---|---|---|"]
    for r in rows:
        status, reason = r["after_on"] or ("-", "")
        lines.append(f"| {r['group']} | {r['case']} | {r['gap_frames']} frames from "
                     f"{r['gap_first']} ({r['gap_s']:.2f} s) | {_m(r['ate_no_gap_m'])} | "
                     f"{_m(r['ate_off_m'])} | {_m(r['ate_on_m'])} | {status}: "
                     f"{reason.split(':')[0] if reason else '-'} |")
    return "\n".join(lines)


def summary(rows: list[dict]) -> str:
    lines = []
    for group in dict.fromkeys(r["group"] for r in rows):
        for motion in dict.fromkeys(r["motion"] for r in rows):
            sel = [r for r in rows if r["group"] == group and r["motion"] == motion]
            if not sel:
                continue
            counts = {v: sum(verdict(r) == v for r in sel) for v in ("better", "worse", "same")}
            ratios = [r["ate_on_m"] / r["ate_off_m"] for r in sel
                      if r["ate_on_m"] and r["ate_off_m"]]  # fmt: skip
            lines.append(f"stall_table: {group}, {motion}: with the check better on "
                         f"{counts['better']}, worse on {counts['worse']}, the same on "
                         f"{counts['same']} of {len(sel)} gaps; ATE with / without "
                         f"{statistics.geometric_mean(ratios):.2f}x in geometric mean"
                         if ratios else f"stall_table: {group}, {motion}: no ATE")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m rsvo_ros.tools.stall_table", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--frames", type=int, default=210, help="frames rendered per case (210)")
    p.add_argument("--jobs", type=int, default=1, help="cases run side by side (1)")
    p.add_argument("--cases", type=int, default=None, metavar="N", help="only the first N cases")
    p.add_argument("--json", default=None, metavar="FILE", help="also write the rows here")
    args = p.parse_args(argv)
    if args.jobs < 1 or (args.cases is not None and args.cases < 1):
        print("stall_table: --jobs and --cases must be at least 1", file=sys.stderr)
        return 2
    cases = CASES[:args.cases]
    if any(first + count >= args.frames for *_, gaps in cases for first, count in gaps):
        print(f"stall_table: --frames {args.frames} leaves no frame after a gap (the last "
              f"ends at frame {max(f + c for *_, g in cases for f, c in g)})", file=sys.stderr)
        return 2
    jobs = [(*c, args.frames) for c in cases]
    per_case = run_cases(run_case, jobs, args.jobs, lambda k, n, rows: (
        f"[stall_table {k}/{n}] {rows[0]['case']}: " + ", ".join(
            f"{r['gap_frames']} frames {_m(r['ate_off_m'])} -> {_m(r['ate_on_m'])} m"
            for r in rows)))
    rows = [r for case_rows in per_case for r in case_rows]
    if args.json:
        with open(args.json, "w") as f:
            json.dump(rows, f, indent=1)
    print(table(rows) + "\n\n" + summary(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
