"""The README's auto-exposure table: brightness that changes from frame to frame.

    python -m rsvo_ros.tools.brightness_table OUT [--frames 150] [--jobs 2]

For each case a bag is written (``rsvo_synth --gain-variation A``: each frame's brightness
times ``exp(A g(t))``, g a smooth random signal of unit RMS) and replayed with the RS model with
the tracker's photometric compensation (the default) and without it
(``--no-photometric-compensation``), with the GS model (compensated), and, for the cases that
have one, the same bag at constant brightness (A = 0) with the RS model. Groups: "looked at"
(seeds 740-745) were replayed while the compensation was built; "chose the prediction" (seeds
750-757) decided that each image starts from the last image's change; "held out" (seeds
760-765) were written after the method was fixed and changed nothing. Writes
``brightness.md`` (the table and geometric means), ``brightness.json`` and ``brightness.png``
into OUT.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from rsvo_ros.odometry.pipeline import PipelineOptions
from rsvo_ros.sim.synth import SynthConfig
from rsvo_ros.tools.rate_table import run_cases
from rsvo_ros.tools.replay import ReplayConfig, replay
from rsvo_ros.tools.synth_bag import write_bag

LOOKED_AT = [("walk", 1.0, 740), ("walk", 1.0, 741), ("walk", 2.0, 742),
             ("handheld", 1.0, 743), ("vehicle", 1.0, 744), ("walk", 1.0, 745)]
CHOSE = [("walk", 1.0, 750), ("walk", 1.0, 751), ("walk", 1.0, 752), ("walk", 1.0, 753),
         ("handheld", 1.0, 754), ("handheld", 1.0, 755), ("vehicle", 1.0, 756),
         ("vehicle", 1.0, 757)]
HELD_OUT = [("walk", 1.0, 760), ("walk", 1.0, 761), ("walk", 2.0, 762),
            ("handheld", 1.0, 763), ("vehicle", 1.0, 764), ("vehicle", 2.0, 765)]
# (group, motion, severity, seed, gain variation, with the constant-brightness twin: replayed
# once per seed, its ATE shared by the seed's other rows)
CASES = [
    *[("looked at", m, s, n, a, a == 0.2) for a in (0.2, 0.4) for m, s, n in LOOKED_AT],
    *[("chose the prediction", m, s, n, 0.3, False) for m, s, n in CHOSE],
    *[("held out", m, s, n, 0.3, True) for m, s, n in HELD_OUT],
]  # fmt: skip


def _bag(out: Path, motion: str, severity: float, seed: int, gain: float,
         frames: int) -> Path:  # fmt: skip
    bag = out / f"{motion}_sev{severity:g}_seed{seed}_g{gain:g}"
    if not (bag / "metadata.yaml").exists():
        write_bag(bag, SynthConfig(frames=frames, motion=motion, severity=severity, seed=seed,
                                   gain_variation=gain), overwrite=True, progress=False)
    return bag


def _replay(bag: Path, out: Path, model: str, compensate: bool = True) -> dict:
    options = PipelineOptions()
    options.tracker.photometric_compensation = compensate
    return replay(ReplayConfig(bag, out, model=model, overwrite=True, progress=False,
                               options=options))


def run_case(out: Path, group: str, motion: str, severity: float, seed: int, gain: float,
             twin: bool, frames: int) -> dict:  # fmt: skip
    bag = _bag(out, motion, severity, seed, gain, frames)
    row = {"case": bag.name, "group": group, "motion": motion, "severity": severity,
           "seed": seed, "gain_variation": gain}
    on = _replay(bag, out / f"{bag.name}__rs", "rs")
    row["frames_compensated"] = on["frames_brightness_compensated"]
    row["frames"] = on["frames_in"]
    row["ate_rs_m"] = on["accuracy"]["ate_m"]["rmse"]
    row["ate_rs_uncompensated_m"] = _replay(bag, out / f"{bag.name}__rs_off", "rs",
                                            False)["accuracy"]["ate_m"]["rmse"]
    row["ate_gs_m"] = _replay(bag, out / f"{bag.name}__gs", "gs")["accuracy"]["ate_m"]["rmse"]
    row["ate_rs_constant_m"] = None
    if twin:
        flat = _bag(out, motion, severity, seed, 0.0, frames)
        s = _replay(flat, out / f"{flat.name}__rs", "rs")
        row["ate_rs_constant_m"] = s["accuracy"]["ate_m"]["rmse"]
    return row


def _geomean(x) -> float:
    return float(np.exp(np.mean(np.log(np.asarray(x, float)))))


def summary(rows: list[dict]) -> str:
    """Per group and gain variation: geometric means of the ATE ratios, and on how many bags
    the compensation and the RS model won."""
    out = []
    for key in dict.fromkeys((r["group"], r["gain_variation"]) for r in rows):
        g = [r for r in rows if (r["group"], r["gain_variation"]) == key]
        on = np.array([r["ate_rs_m"] for r in g])
        off = np.array([r["ate_rs_uncompensated_m"] for r in g])
        gs = np.array([r["ate_gs_m"] for r in g])
        line = (f"- {key[0]}, gain variation {key[1]:g} ({len(g)} bags): RS compensated / not "
                f"{_geomean(on / off):.2f} (better on {int(np.sum(on < off))}), RS / GS "
                f"{_geomean(on / gs):.2f} (RS better on {int(np.sum(on < gs))}; not "
                f"compensated {_geomean(off / gs):.2f})")
        if all(r["ate_rs_constant_m"] is not None for r in g):
            flat = np.array([r["ate_rs_constant_m"] for r in g])
            line += (f"; against the same bags at constant brightness: compensated "
                     f"{_geomean(on / flat):.2f}, not {_geomean(off / flat):.2f}")
        out.append(line)
    return "\n".join(out)


def table(rows: list[dict]) -> str:
    lines = ["| bag | group | gain variation | frames mapped | RS, constant brightness | RS | "
             "RS, not compensated | GS |", "|---" * 8 + "|"]
    for r in rows:
        flat = "-" if r["ate_rs_constant_m"] is None else f"{r['ate_rs_constant_m']:.3f}"
        lines.append(f"| {r['motion']} sev. {r['severity']:g}, seed {r['seed']} | {r['group']} "
                     f"| {r['gain_variation']:g} | {r['frames_compensated']} of {r['frames']} "
                     f"| {flat} | {r['ate_rs_m']:.3f} | {r['ate_rs_uncompensated_m']:.3f} | "
                     f"{r['ate_gs_m']:.3f} |")
    return "\n".join(lines)


def plot(path: Path, rows: list[dict]) -> None:
    """ATE per bag (log scale): RS compensated, not compensated, GS, constant brightness."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(11, 4.2))
    x = np.arange(len(rows))
    for key, label, marker, colour in (
            ("ate_rs_constant_m", "RS, constant brightness", "_", "k"),
            ("ate_rs_uncompensated_m", "RS, not compensated", "v", "tab:red"),
            ("ate_gs_m", "GS (compensated)", "s", "tab:gray"),
            ("ate_rs_m", "RS (compensated)", "o", "tab:blue")):  # fmt: skip
        y = np.array([np.nan if r[key] is None else r[key] for r in rows], float)
        ax.plot(x, y, marker, color=colour, label=label, ms=8 if marker == "_" else 5,
                mew=2 if marker == "_" else 1, ls="none")
    ax.set_yscale("log")
    ax.set_xticks(x, [f"{r['motion'][:4]} {r['severity']:g} #{r['seed']}\n"
                      f"A={r['gain_variation']:g}" for r in rows], fontsize=6, rotation=90)
    ax.set_ylabel("ATE (m, Sim(3))")
    ax.set_title("auto exposure (rsvo_synth --gain-variation A): tracking in the previous "
                 "image's grey levels", fontsize=9)
    ax.legend(fontsize=8), ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m rsvo_ros.tools.brightness_table",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path)
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--jobs", type=int, default=1, help="cases replayed side by side (1)")
    args = p.parse_args(argv)
    if args.frames < 2 or args.jobs < 1:
        print("brightness_table: --frames must be at least 2 and --jobs at least 1",
              file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = [(args.out, *case, args.frames) for case in CASES]
    rows = run_cases(run_case, jobs, args.jobs, lambda k, n, row: (
        f"[brightness_table] {row['case']}: RS {row['ate_rs_m']:.3f} m, not compensated "
        f"{row['ate_rs_uncompensated_m']:.3f} m, GS {row['ate_gs_m']:.3f} m "
        f"({row['frames_compensated']} of {row['frames']} frames mapped)"))
    flat = {(r["motion"], r["severity"], r["seed"]): r["ate_rs_constant_m"] for r in rows
            if r["ate_rs_constant_m"] is not None}
    for r in rows:
        r["ate_rs_constant_m"] = flat.get((r["motion"], r["severity"], r["seed"]))
    (args.out / "brightness.json").write_text(json.dumps(rows, indent=1))
    (args.out / "brightness.md").write_text(table(rows) + "\n\n" + summary(rows) + "\n")
    plot(args.out / "brightness.png", rows)
    print(summary(rows))
    print(f"wrote {args.out / 'brightness.md'}, brightness.json, brightness.png")
    return 0


if __name__ == "__main__":
    sys.exit(main())
