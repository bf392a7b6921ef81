"""The README's moving-people table: odometry with pedestrians walking in front of the camera.

    python -m rsvo_ros.tools.movers_table OUT [--frames 90] [--jobs 2]

For each case a sharp 30 Hz bag is written with 0, 2 and 4 people (``rsvo_synth --movers N
--frames 90 --motion M --seed K``: pedestrian-sized textured panels 3-6 m in front of the
camera, crossing the view or walking along it; the bag without people is the same bag
otherwise) and replayed with the defaults (window backend), RS and GS. Seeds 820-822 were
looked at (the window's first-map check against the bootstrap chain was found on them), 823-825
were written afterwards (and used in the twenty-first session's comparisons); 830-832 were
written in the twenty-first session and used only to check a change chosen on the others
(it was not kept). Writes ``movers.md`` (per bag and per group), ``movers.json`` and
``movers.png`` (ATE with people against ATE without, per motion) into OUT.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from rsvo_ros.sim.synth import SynthConfig
from rsvo_ros.tools.rate_table import (
    MOTION_COLOURS,
    fmt,
    gmean,
    ratio,
    replay_row,
    run_cases,
)
from rsvo_ros.tools.synth_bag import write_bag

MOVERS = (0, 2, 4)
CASES = [(m, 1.0, seed, group) for m in ("walk", "handheld", "vehicle")
         for seed, group in ((820, "looked at"), (821, "looked at"), (822, "looked at"),
                             (823, "fresh"), (824, "fresh"), (825, "fresh"),
                             (830, "held out"), (831, "held out"), (832, "held out"))]


def run_case(out: Path, motion: str, severity: float, seed: int, group: str, movers: int,
             frames: int) -> dict:
    """Write (or reuse) the case's bag, replay it with RS and GS and return its row."""
    bag = out / f"{motion}_sev{severity:g}_seed{seed}_movers{movers}"
    if not (bag / "metadata.yaml").exists():
        write_bag(bag, SynthConfig(frames=frames, motion=motion, severity=severity, seed=seed,
                                   movers=movers), overwrite=True, progress=False)
    return {"case": bag.name, "motion": motion, "severity": severity, "seed": seed,
            "group": group, "movers": movers,
            "rs": replay_row(bag, out / f"{bag.name}__rs", "rs"),
            "gs": replay_row(bag, out / f"{bag.name}__gs", "gs")}


def _without(rows: list[dict], r: dict) -> dict | None:
    """The same bag without people."""
    return next((q for q in rows if q["motion"] == r["motion"] and q["seed"] == r["seed"]
                 and q["movers"] == 0), None)  # fmt: skip


def table(rows: list[dict]) -> str:
    lines = ["| bag | people | RS ATE | GS ATE | RS / GS | RS ATE against no people | RS RPE "
             "rotation per frame | RS inlier ratio | frames with a pose (held) |",
             "|---" * 9 + "|"]
    for r in rows:
        rs, gs = r["rs"], r["gs"]
        base = _without(rows, r)
        rel = None if base is None else ratio(rs["ate_m"], base["rs"]["ate_m"])
        lines.append(
            f"| {r['motion']} sev. {r['severity']:g}, seed {r['seed']} ({r['group']}) | "
            f"{r['movers']} | {fmt(rs['ate_m'], '.3f')} m | {fmt(gs['ate_m'], '.3f')} m | "
            f"{fmt(ratio(rs['ate_m'], gs['ate_m']), '.2f')} | {fmt(rel, '.2f')} | "
            f"{fmt(rs['rpe_rot_deg'], '.3f')} deg | {fmt(rs['inlier_ratio'], '.2f')} | "
            f"{rs['posed']} ({rs['held']}) of {rs['frames']} |")
    return "\n".join(lines)


def summary(rows: list[dict]) -> str:
    """Per group, motion and number of people: RS ATE against the same bags without people
    and RS / GS, in geometric mean with their ranges."""
    out = []
    for group in dict.fromkeys(r["group"] for r in rows):
        for motion in dict.fromkeys(r["motion"] for r in rows):
            for n in MOVERS:
                rs = [r for r in rows if r["group"] == group and r["motion"] == motion
                      and r["movers"] == n]  # fmt: skip
                if not rs:
                    continue
                rel = [ratio(r["rs"]["ate_m"], (_without(rows, r) or {"rs": {}})["rs"]
                              .get("ate_m")) for r in rs]  # fmt: skip
                vs = [ratio(r["rs"]["ate_m"], r["gs"]["ate_m"]) for r in rs]
                known = [x for x in vs if x is not None]
                out.append(
                    f"- {group}, {motion}, {n} people ({len(rs)} bags): RS ATE "
                    f"{fmt(gmean(r['rs']['ate_m'] for r in rs), '.3f')} m in geometric mean"
                    + ("" if n == 0 else f", {fmt(gmean(rel), '.2f')}x the same bags without")
                    + f"; RS / GS {fmt(gmean(vs), '.2f')} (RS better on "
                    f"{sum(x < 1 for x in known)} of {len(known)})")
    return "\n".join(out)


def plot(path: Path, rows: list[dict]) -> None:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, 2, figsize=(11, 3.8))
    jitter = {m: (i - 1) * 0.12 for i, m in enumerate(MOTION_COLOURS)}
    for motion, colour in MOTION_COLOURS.items():
        for which, ax in (("rs", axes[0]), ("gs", axes[1])):
            pts = [(r["movers"] + jitter[motion], r[which]["ate_m"]) for r in rows
                   if r["motion"] == motion and r[which]["ate_m"] is not None]  # fmt: skip
            if pts:
                x, y = np.array(pts).T
                ax.plot(x, y, "o", color=colour, mfc="none", label=motion)
    for ax, title in ((axes[0], "RS (window backend)"), (axes[1], "GS (window backend)")):
        ax.set_yscale("log")
        ax.yaxis.set_major_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.yaxis.set_minor_locator(matplotlib.ticker.LogLocator(subs=(2.0, 5.0)))
        ax.yaxis.set_minor_formatter(matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}"))
        ax.set_xticks(MOVERS)
        ax.set_xlabel("people walking in front of the camera")
        ax.set_ylabel("ATE (m, after Sim(3))")
        ax.set_title(title, fontsize=9)
        ax.grid(alpha=0.3)
        ax.legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m rsvo_ros.tools.movers_table", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path)
    p.add_argument("--frames", type=int, default=90)
    p.add_argument("--jobs", type=int, default=1, help="cases replayed side by side (1)")
    args = p.parse_args(argv)
    if args.frames < 10 or args.jobs < 1:
        print("movers_table: --frames must be at least 10 and --jobs at least 1",
              file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = [(args.out, *c, n, args.frames) for c in CASES for n in MOVERS]
    rows = run_cases(run_case, jobs, args.jobs, lambda k, n, row: (
        f"[movers_table {k}/{n}] {row['case']}: RS ATE {fmt(row['rs']['ate_m'], '.3f')} m, "
        f"GS {fmt(row['gs']['ate_m'], '.3f')} m"))
    (args.out / "movers.json").write_text(json.dumps(rows, indent=1))
    (args.out / "movers.md").write_text(table(rows) + "\n\n" + summary(rows) + "\n")
    plot(args.out / "movers.png", rows)
    print(summary(rows))
    print(f"wrote {args.out / 'movers.md'}, movers.json, movers.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
