"""The README's replay tables: synthetic bags (``rsvo_synth``) replayed (``rsvo_replay``) with
each model and backend; every figure is read from the replays' ``summary.json``.

    python -m rsvo_ros.tools.replay_table OUT [--only vehicle|walk] [--hd]

- vehicle: 60 frames, 640x360, a 30 Hz camera on a shaking vehicle (``--severity`` 1 and 2,
  seeds 0-15; 8-15 were held out while the pairwise motion prior was tuned) and the same
  without rolling shutter (``--line-delay 0``);
- walk: hand-held walks (``--motion walk``), 90 frames (mild, strong, strongest shake) and 300
  frames, tuning seeds and held-out seeds (100-) reported apart.

Columns: ATE (RMSE after Sim(3)) of the RS and GS models with the window and the pairwise
backend (and, for vehicles, RS pairwise without the motion prior: the paper's setting), and the
RS window with the paper's constant velocity within a frame (the default estimates each
frame's angular acceleration during its readout, prior std ``ACCELERATION_STD_RAD_S2``).
Writes ``tables.md``, ``rows.json`` and ``replay_ate.png`` into OUT.
"""

from __future__ import annotations

import argparse
import json
import math
import sys
from pathlib import Path

import numpy as np

from rsvo_ros.odometry.local_map import ACCELERATION_STD_RAD_S2
from rsvo_ros.odometry.pipeline import PipelineOptions
from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig
from rsvo_ros.tools.replay import ReplayConfig, replay
from rsvo_ros.tools.synth_bag import write_bag

CONSTANT = "RS window, constant velocity"
VARIANTS = {  # column -> (model, backend, motion prior, angular acceleration std)
    "RS window": ("rs", "window", True, ACCELERATION_STD_RAD_S2),
    "GS window": ("gs", "window", True, 0.0),  # no readout: nothing to turn during it
    "RS pairwise": ("rs", "pairwise", True, 0.0),
    "GS pairwise": ("gs", "pairwise", True, 0.0),
    "RS pairwise, no prior": ("rs", "pairwise", False, 0.0),
    CONSTANT: ("rs", "window", True, 0.0),
}


def vehicle_cases() -> list[tuple[str, str, dict]]:
    cases = []
    for seed in range(4):
        cases.append(("severity 1", f"--severity 1 --seed {seed}",
                      dict(motion="vehicle", severity=1.0, seed=seed)))
    for seed in range(16):
        group = "severity 2" if seed < 8 else "severity 2 (held out)"
        cases.append((group, f"--severity 2 --seed {seed}",
                      dict(motion="vehicle", severity=2.0, seed=seed)))
    for seed in range(4):
        cases.append(("no RS", f"--severity 2 --seed {seed} --line-delay 0",
                      dict(motion="vehicle", severity=2.0, seed=seed, line_delay=0.0)))
    return [(g, o, dict(c, frames=60)) for g, o, c in cases]


def walk_cases() -> list[tuple[str, str, dict]]:
    cases = []
    for group, seeds in (("walk", (0,)), ("walk (held out)", (100, 101))):
        for sev, name in ((0.5, "mild"), (1.0, "strong"), (2.0, "strongest")):
            for seed in seeds:
                cases.append((f"{group}, {name}", f"--severity {sev:g} --seed {seed}",
                              dict(motion="walk", severity=sev, seed=seed, frames=90)))
        for seed in seeds:
            cases.append((f"{group}, 300 frames", f"--severity 0.7 --seed {seed} --frames 300",
                          dict(motion="walk", severity=0.7, seed=seed, frames=300)))
    cases.append(("walk, no RS", "--severity 1 --seed 0 --line-delay 0",
                  dict(motion="walk", severity=1.0, seed=0, frames=90, line_delay=0.0)))
    return cases


def run_case(out: Path, name: str, config: dict, columns: list[str]) -> dict:
    bag = out / name
    if not (bag / "metadata.yaml").exists():
        write_bag(bag, SynthConfig(**config), overwrite=True, progress=False)
    row = {}
    path = _path_length(bag)
    renderer = SequenceRenderer(SynthConfig(**config))  # the truth over each readout
    for col in columns:
        model, backend, prior, acc_std = VARIANTS[col]
        dest = out / f"{name}__{col.replace(' ', '_').replace(',', '')}"
        options = PipelineOptions(motion_prior=prior, backend=backend)
        options.window.map.prior_acc_rad_s2 = acc_std
        s = replay(ReplayConfig(bag, dest, model, overwrite=True, progress=False,
                                options=options))  # fmt: skip
        acc = s["accuracy"]
        row[col] = {"ate_m": acc["ate_m"]["rmse"], "path_m": path,
                    "sim3_scale": acc["sim3_scale"], "rpe_rot_deg": acc["rpe_rot_deg"]["rmse"],
                    "with_pose": s["frames_posed"] / s["frames_in"],
                    "held": s["frames_held"], "fps": s["frames_per_second"],
                    "keyframe_w_rel_error": s.get("keyframes", {}).get("w_rel_error_median"),
                    "scale_rate_percent_per_s": acc.get("scale_rate", {}).get("percent_per_s")}
        if backend == "window":
            row[col].update(readout_w_errors(renderer, s.get("keyframes", {})))
    return row


def readout_w_errors(renderer: SequenceRenderer, keyframes: dict) -> dict:
    """The keyframes' turn rates against the mean turn rate over each frame's readout (what a
    constant velocity within a frame can represent; ``renderer`` of the bag's sequence), and
    how far that mean itself is from the instantaneous row-0 rate the bag's ground truth
    carries (the floor of the error the summary reports): medians relative to the
    reference's ``|w|``."""
    est, floor = [], []
    for kf in keyframes.get("velocities", []):
        k = round(kf["stamp_ns"] * 1e-9 * renderer.config.rate_hz)
        if not 0 <= k < renderer.config.frames:
            continue
        w_mean = renderer.readout_turn_rate(k)
        w_inst = renderer.frame_pose(k)[3]
        if np.linalg.norm(w_mean) < 1e-6 or np.linalg.norm(w_inst) < 1e-6:
            continue
        est.append(np.linalg.norm(np.asarray(kf["w"]) - w_mean) / np.linalg.norm(w_mean))
        floor.append(np.linalg.norm(w_mean - w_inst) / np.linalg.norm(w_inst))
    if not est:
        return {}
    return {"keyframe_w_readout_error": float(np.median(est)),
            "readout_w_vs_instantaneous": float(np.median(floor))}


def _path_length(bag: Path) -> float:
    from rsvo_ros.tools.compare import read_ground_truth

    gt = read_ground_truth(bag)
    p = np.array([gt[s][:3, 3] for s in sorted(gt)])
    return float(np.linalg.norm(np.diff(p, axis=0), axis=1).sum())


def _geo(v):
    v = [x for x in v if x and x > 0]
    return math.exp(sum(map(math.log, v)) / len(v)) if v else float("nan")


def format_table(title: str, rows: list, columns: list[str]) -> str:
    lines = [f"| {title} | " + " | ".join(f"{c} ATE" for c in columns)
             + " | RS window / GS window | RS window / RS pairwise |",
             "|---|" + "---|" * (len(columns) + 2)]
    for _group, opts, row in rows:
        cells = []
        for c in columns:
            r = row[c]
            pct = 100 * r["ate_m"] / max(r["path_m"], 1e-9)
            cells.append(f"{r['ate_m']:.3f} m ({pct:.1f} %)")
        a, b, p = row["RS window"]["ate_m"], row["GS window"]["ate_m"], \
            row["RS pairwise"]["ate_m"]
        lines.append(f"| {opts} | " + " | ".join(cells) + f" | {a / b:.2f} | {a / p:.2f} |")
    lines.append("")
    groups = sorted({g for g, _, _ in rows}, key=[g for g, _, _ in rows].index)
    for g in groups:
        sel = [row for gg, _, row in rows if gg == g]
        w_gs = _geo([r["RS window"]["ate_m"] / r["GS window"]["ate_m"] for r in sel])
        w_pw = _geo([r["RS window"]["ate_m"] / r["RS pairwise"]["ate_m"] for r in sel])
        pct = max(100 * r["RS window"]["ate_m"] / r["RS window"]["path_m"] for r in sel)
        rpe = max(r["RS window"]["rpe_rot_deg"] for r in sel)
        kw = [r["RS window"]["keyframe_w_rel_error"] for r in sel
              if r["RS window"]["keyframe_w_rel_error"] is not None]
        # a constant velocity within a frame can only represent the mean over its readout
        cv = CONSTANT if CONSTANT in columns else "RS window"
        kr = [r[cv]["keyframe_w_readout_error"] for r in sel
              if r[cv].get("keyframe_w_readout_error") is not None]
        fl = [r[cv]["readout_w_vs_instantaneous"] for r in sel
              if r[cv].get("readout_w_vs_instantaneous") is not None]
        acc = ""
        rates = {c: [r[c]["scale_rate_percent_per_s"] for r in sel
                     if r[c].get("scale_rate_percent_per_s") is not None]
                 for c in ("RS window", "RS pairwise")}  # fmt: skip
        win = rates["RS window"]
        if win:
            acc += (f"; scale change (median, % per s) RS window {np.median(win):+.1f} "
                    f"({sum(x < 0 for x in win)} of {len(win)} shrinking)")
            if rates["RS pairwise"]:
                acc += f", RS pairwise {np.median(rates['RS pairwise']):+.1f}"
        if CONSTANT in columns:
            ratio = _geo([r[CONSTANT]["ate_m"] / r["RS window"]["ate_m"] for r in sel])
            rpe_cv = _geo([r[CONSTANT]["rpe_rot_deg"] / r["RS window"]["rpe_rot_deg"]
                           for r in sel])
            acc += (f"; constant velocity within a frame / with the angular acceleration: ATE "
                    f"{ratio:.2f}, RPE rotation {rpe_cv:.2f}")
        lines.append(f"- {g} ({len(sel)}): RS window / GS window geometric mean {w_gs:.2f}, "
                     f"RS window / RS pairwise {w_pw:.2f}; RS window worst {pct:.1f} % of the "
                     f"path, RPE rotation up to {rpe:.2f} deg per frame"
                     + (f", keyframe |w| error median {100 * np.median(kw):.0f} %" if kw
                        else "")
                     + (f" (constant velocity: against the mean over the readout "
                        f"{100 * np.median(kr):.0f} %, that mean {100 * np.median(fl):.0f} % "
                        "off the instantaneous row-0 rate)" if kr else "") + acc)
    return "\n".join(lines)


def plot(path: Path, rows: list, columns: list[str]) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    names = [opts.replace("--severity ", "s").replace(" --seed ", "/").replace(
        " --line-delay 0", " LD0").replace(" --frames 300", " 300f") for _, opts, _ in rows]
    x = np.arange(len(rows))
    fig, ax = plt.subplots(figsize=(max(8, 0.45 * len(rows)), 4))
    colours = {"RS window": "tab:red", "GS window": "tab:blue", "RS pairwise": "tab:orange",
               "GS pairwise": "tab:cyan", "RS pairwise, no prior": "tab:gray",
               CONSTANT: "tab:purple"}
    width = 0.8 / len(columns)
    for j, c in enumerate(columns):
        ax.bar(x + (j - (len(columns) - 1) / 2) * width, [r[c]["ate_m"] for _, _, r in rows],
               width, label=c, color=colours[c])
    ax.set_yscale("log")
    ax.set_xticks(x, names, rotation=60, fontsize=7)
    ax.set_ylabel("ATE after Sim(3) (m)")
    ax.grid(axis="y", alpha=0.3)
    ax.legend(fontsize=8)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="python -m rsvo_ros.tools.replay_table",
                                 description=__doc__,
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("out", type=Path)
    ap.add_argument("--only", choices=("vehicle", "walk"), default=None)
    args = ap.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    parts = []
    all_rows = {}
    walk_columns = [c for c in VARIANTS if c != "RS pairwise, no prior"]
    for kind, cases, columns in (("vehicle", vehicle_cases(), list(VARIANTS)),
                                 ("walk", walk_cases(), walk_columns)):
        if args.only and args.only != kind:
            continue
        rows = []
        for group, opts, config in cases:
            name = f"{kind}_" + opts.replace("--", "").replace(" ", "_")
            rows.append((group, opts, run_case(args.out, name, config, columns)))
            print(f"[replay_table] {kind} {opts}: " + ", ".join(
                f"{c} {rows[-1][2][c]['ate_m']:.3f} m" for c in columns), file=sys.stderr)
        title = ("rsvo_synth options (vehicle, 60 frames, 640x360)" if kind == "vehicle"
                 else "rsvo_synth --motion walk options (640x360; 90 frames unless said)")
        parts.append(format_table(title, rows, columns))
        plot(args.out / f"replay_ate_{kind}.png", rows, columns)
        all_rows[kind] = [(g, o, r) for g, o, r in rows]
    text = "\n\n".join(parts)
    (args.out / "tables.md").write_text(text + "\n")
    (args.out / "rows.json").write_text(json.dumps(all_rows, indent=1))
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
