"""The README's frame-rate table: the same motions filmed at 10, 15, 30 and 60 Hz.

    python -m rsvo_ros.tools.rate_table OUT [--seconds 4] [--jobs 2]

For each case a sharp bag is written (``rsvo_synth --rate HZ --frames 4*HZ --motion M --seed
K --line-delay 4e-5``: the same continuous motion sampled at each rate, one readout of 14.4 ms
at 360 rows, what a sensor keeps when its frame rate changes) and replayed with the defaults
(window backend) three times: RS with the true line delay, GS, and RS with ``line_delay auto``
(the online pass, as the node runs). Nothing was tuned on these bags (seeds 810-812, first run
2026-11-26). Writes ``rate.md`` (per bag and per rate), ``rate.json`` and ``rate.png`` (RS / GS
ATE and the RS per-frame rotation error against the frame rate) into OUT.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import multiprocessing
import sys
from pathlib import Path

import numpy as np

from rsvo_ros.odometry.pipeline import PipelineOptions
from rsvo_ros.sim.synth import SynthConfig
from rsvo_ros.tools.replay import ReplayConfig, replay
from rsvo_ros.tools.synth_bag import write_bag

RATES_HZ = (10.0, 15.0, 30.0, 60.0)
LINE_DELAY_S = 4e-5  # 14.4 ms at 360 rows: under one frame interval at 60 Hz
MOTION_COLOURS = {"walk": "tab:blue", "handheld": "tab:orange", "vehicle": "tab:green"}
CASES = [(m, 1.0, seed) for m in ("walk", "handheld", "vehicle") for seed in (810, 811, 812)]


def replay_row(bag: Path, out: Path, model: str, auto: bool = False) -> dict:
    """Replay ``bag`` with the defaults (``model``; ``auto``: line delay auto, the online pass)
    and return the row's accuracy and frame counts (also used by ``movers_table``)."""
    s = replay(ReplayConfig(bag, out, model=model, overwrite=True, progress=False,
                            options=PipelineOptions(model=model, line_delay_auto=auto)))
    acc = s.get("accuracy") or {}
    row = {"ate_m": (acc.get("ate_m") or {}).get("rmse"),
           "rpe_rot_deg": (acc.get("rpe_rot_deg") or {}).get("rmse"),
           "scale_drift": (acc.get("scale_drift") or {}).get("ratio"),
           "posed": s["frames_posed"], "held": s["frames_held"], "frames": s["frames_in"],
           "inlier_ratio": s["inlier_ratio_mean"]}
    if auto:
        est = s["line_delay_auto"]
        row.update(status=est["status"], line_delay_s=est.get("line_delay_s"),
                   estimate_frames=est.get("frames"))
    return row


def run_case(out: Path, motion: str, severity: float, seed: int, rate: float,
             seconds: float) -> dict:
    """Write (or reuse) the case's bag, replay it three ways and return its row."""
    bag = out / f"{motion}_sev{severity:g}_seed{seed}_{rate:g}hz"
    frames = int(round(seconds * rate))
    if not (bag / "metadata.yaml").exists():
        write_bag(bag, SynthConfig(frames=frames, motion=motion, severity=severity, seed=seed,
                                   line_delay=LINE_DELAY_S, frame_rate=rate),
                  overwrite=True, progress=False)  # fmt: skip
    return {"case": bag.name, "motion": motion, "severity": severity, "seed": seed,
            "rate_hz": rate, "frames": frames,
            "rs": replay_row(bag, out / f"{bag.name}__rs", "rs"),
            "gs": replay_row(bag, out / f"{bag.name}__gs", "gs"),
            "auto": replay_row(bag, out / f"{bag.name}__auto", "rs", auto=True)}


def ratio(a, b):
    """``a / b``, None where either is missing or ``b`` is not positive."""
    return None if a is None or b is None or b <= 0 else a / b


def fmt(x, spec: str) -> str:
    """``x`` formatted, ``-`` for None."""
    return "-" if x is None else format(x, spec)


def table(rows: list[dict]) -> str:
    lines = ["| bag | rate | frames with a pose (held) | RS ATE | GS ATE | RS / GS | RPE "
             "rotation per frame, RS / GS | line delay auto (true 40 us/row) | ATE auto / true |",
             "|---" * 9 + "|"]
    for r in rows:
        rs, gs, auto = r["rs"], r["gs"], r["auto"]
        est = auto.get("line_delay_s")
        est_text = "-" if est is None else \
            f"{est * 1e6:.1f} us/row ({100 * (est / LINE_DELAY_S - 1):+.0f} %)"
        lines.append(
            f"| {r['motion']} sev. {r['severity']:g}, seed {r['seed']} | {r['rate_hz']:g} Hz | "
            f"{rs['posed']} ({rs['held']}) of {rs['frames']} | {fmt(rs['ate_m'], '.3f')} m | "
            f"{fmt(gs['ate_m'], '.3f')} m | {fmt(ratio(rs['ate_m'], gs['ate_m']), '.2f')} | "
            f"{fmt(rs['rpe_rot_deg'], '.3f')} / {fmt(gs['rpe_rot_deg'], '.3f')} deg | "
            f"{est_text} | {fmt(ratio(auto['ate_m'], rs['ate_m']), '.2f')} |")
    return "\n".join(lines)


def gmean(values) -> float | None:
    """The geometric mean of the positive values (None missing); None without any."""
    v = [x for x in values if x is not None and x > 0]
    return float(np.exp(np.mean(np.log(v)))) if v else None


def summary(rows: list[dict]) -> str:
    """Per frame rate: RS / GS in geometric mean and its range, frames posed, RS per-frame
    rotation error, the line-delay estimates within 10 % and auto's ATE within 10 % of true."""
    out = []
    for rate in dict.fromkeys(r["rate_hz"] for r in rows):
        rs = [r for r in rows if r["rate_hz"] == rate]
        ratios = [ratio(r["rs"]["ate_m"], r["gs"]["ate_m"]) for r in rs]
        known = [x for x in ratios if x is not None]
        posed = sum(r["rs"]["posed"] for r in rs)
        frames = sum(r["rs"]["frames"] for r in rs)
        est = [r["auto"].get("line_delay_s") for r in rs]
        within = sum(e is not None and abs(e / LINE_DELAY_S - 1) <= 0.1 for e in est)
        auto_ok = sum((x := ratio(r["auto"]["ate_m"], r["rs"]["ate_m"])) is not None
                      and x <= 1.1 for r in rs)  # fmt: skip
        gm = gmean(ratios)
        lo, hi = (min(known), max(known)) if known else (None, None)
        out.append(
            f"- {rate:g} Hz ({len(rs)} bags): RS / GS ATE {fmt(gm, '.2f')} in geometric mean "
            f"({fmt(lo, '.2f')}-{fmt(hi, '.2f')}; RS better on {sum(x < 1 for x in known)}), "
            f"frames posed {posed} of {frames}, RS rotation error per frame "
            f"{fmt(gmean(r['rs']['rpe_rot_deg'] for r in rs), '.3f')} deg (GS "
            f"{fmt(gmean(r['gs']['rpe_rot_deg'] for r in rs), '.3f')}); line delay "
            f"auto within 10 % on {within}, its ATE within 10 % of the true line delay's on "
            f"{auto_ok}")
    return "\n".join(out)


def plot(path: Path, rows: list[dict]) -> None:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    for motion, colour in MOTION_COLOURS.items():
        rs = [r for r in rows if r["motion"] == motion]
        if not rs:
            continue
        x = np.array([r["rate_hz"] for r in rs])
        rs_over_gs = np.array([ratio(r["rs"]["ate_m"], r["gs"]["ate_m"]) or np.nan
                               for r in rs])
        axes[0].plot(x * np.exp(np.random.default_rng(0).uniform(-0.04, 0.04, len(x))), rs_over_gs,
                     "o", color=colour, mfc="none", label=motion)
        for which, marker in (("rs", "o"), ("gs", "x")):
            axes[1].plot(x, [r[which]["rpe_rot_deg"] or np.nan for r in rs], marker,
                         color=colour, ms=4, label=f"{motion} {which.upper()}")
    axes[0].axhline(1.0, color="0.5", lw=1)
    axes[0].set_ylabel("ATE RS / ATE GS")
    axes[0].set_title("RS against GS (window backend)", fontsize=9)
    axes[1].set_ylabel("RPE rotation per frame (deg)")
    axes[1].set_title("per-frame rotation error", fontsize=9)
    for ax in axes:
        ax.set_xscale("log")
        ax.xaxis.set_minor_formatter(matplotlib.ticker.NullFormatter())
        ax.set_xticks(RATES_HZ, [f"{r:g}" for r in RATES_HZ])
        ax.set_xlabel("frame rate (Hz)")
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _call(job: tuple) -> dict:
    fn, args = job
    return fn(*args)


def run_cases(fn, jobs: list[tuple], processes: int, describe) -> list[dict]:
    """``fn(*job)`` for every job on a pool of ``processes`` (the table tools' cases, each a
    bag written and replayed), in order; ``describe(k, n, row)`` is printed as the k-th of n
    rows comes in. Returns the rows. (``fn`` at module level: the pool pickles it.) One
    process: in this one, no pool (a pool forks this process, and a fork of a process with
    threads holding locks, a test runner's with ROS and numba threads, can hang)."""
    rows = []
    calls = [(fn, job) for job in jobs]
    with contextlib.nullcontext() if processes == 1 else multiprocessing.Pool(processes) as pool:
        results = map(_call, calls) if pool is None else pool.imap(_call, calls)
        for k, row in enumerate(results, 1):
            rows.append(row)
            print(describe(k, len(jobs), row), flush=True)
    return rows


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m rsvo_ros.tools.rate_table", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path)
    p.add_argument("--seconds", type=float, default=4.0, help="length of each bag (4 s)")
    p.add_argument("--jobs", type=int, default=1, help="cases replayed side by side (1)")
    args = p.parse_args(argv)
    if not args.seconds >= 1.0 or args.jobs < 1:
        print("rate_table: --seconds must be at least 1 and --jobs at least 1", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = [(args.out, *c, rate, args.seconds) for rate in RATES_HZ for c in CASES]
    rows = run_cases(run_case, jobs, args.jobs, lambda k, n, row: (
        f"[rate_table {k}/{n}] {row['case']}: RS / GS ATE "
        f"{fmt(ratio(row['rs']['ate_m'], row['gs']['ate_m']), '.2f')}"))
    (args.out / "rate.json").write_text(json.dumps(rows, indent=1))
    (args.out / "rate.md").write_text(table(rows) + "\n\n" + summary(rows) + "\n")
    plot(args.out / "rate.png", rows)
    print(summary(rows))
    print(f"wrote {args.out / 'rate.md'}, rate.json, rate.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
