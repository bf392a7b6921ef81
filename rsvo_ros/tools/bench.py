"""rsvo_bench: the paper's synthetic experiment (Sec. 7.1, Table 1) beside the paper's numbers.

Setting (paper Sec. 7.1): 1280x720 images, focal length 5 mm = 1000 px (we assume a 5 um pixel
pitch), tau = 50 us/row, up to 500 evenly spread (bucketed) points of consecutive frames of a
~80 m loop at 5 Hz, RS distortion levels 1-6 (each frame's own instantaneous velocity: the
level's magnitudes in uniformly random directions), noise-free / Gaussian (sigma 1 px) /
Laplacian (sigma 1 px) feature noise, Monte Carlo trials.

Metrics exactly as the paper: ``dT = T_gt T_est^-1`` with the estimate given the ground-truth
translation scale; rotation error = Rodrigues angle of ``dR`` (deg); translation error =
``|dt|`` (m); inlier ratio. Also the pose expressed at the middle row (needs no velocity to be
right) and the velocity errors, which the paper does not report.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

from rsvo_ros.core.geometry import angle_between_deg, pose_at_row, rotation_angle_deg
from rsvo_ros.sim import paper_scene
from rsvo_ros.tools import realpairs
from rsvo_ros.twoview import estimate_relative_pose

NOISE_TYPES = ("none", "gaussian", "laplacian")
NOISE_SIGMA_PX = 1.0  # paper: "The standard deviation of two types of noise is set to 1"
LEVELS = tuple(paper_scene.RS_LEVELS)
DEFAULT_TRIALS = 40
QUICK_TRIALS = 3

# The paper's Table 1 (means, and the inlier ratio in %), per noise type, levels 1-6.
PAPER_TABLE1 = {
    "none": {
        "MVO": {"rot": [0.000, 0.686, 1.266, 1.478, 1.805, 2.093],
                "trans": [0.007, 0.119, 0.203, 0.233, 0.296, 0.284],
                "inlier": [100.0, 44.9, 34.4, 30.2, 27.4, 25.4]},
        "MRSVO": {"rot": [0.007, 0.036, 0.041, 0.052, 0.373, 0.475],
                  "trans": [0.012, 0.026, 0.038, 0.053, 0.085, 0.078],
                  "inlier": [100.0, 99.9, 99.9, 99.5, 97.9, 97.2]},
    },
    "gaussian": {
        "MVO": {"rot": [0.349, 0.704, 1.371, 1.844, 1.955, 2.252],
                "trans": [0.027, 0.085, 0.167, 0.235, 0.249, 0.282],
                "inlier": [23.2, 21.5, 19.4, 18.4, 18.0, 17.4]},
        "MRSVO": {"rot": [0.186, 0.482, 0.657, 0.766, 0.859, 1.045],
                  "trans": [0.017, 0.033, 0.055, 0.097, 0.100, 0.106],
                  "inlier": [51.9, 50.0, 49.2, 48.5, 47.9, 47.7]},
    },
    "laplacian": {
        "MVO": {"rot": [0.401, 0.805, 1.337, 1.675, 2.017, 2.421],
                "trans": [0.032, 0.089, 0.168, 0.204, 0.257, 0.284],
                "inlier": [9.4, 8.7, 8.0, 7.6, 7.4, 7.0]},
        "MRSVO": {"rot": [0.541, 0.820, 0.922, 0.930, 1.064, 1.066],
                  "trans": [0.047, 0.073, 0.100, 0.096, 0.116, 0.121],
                  "inlier": [55.2, 54.7, 53.4, 53.2, 52.9, 50.9]},
    },
}  # fmt: skip

# Our methods: label -> (model, mode)
METHODS = {"MVO (ours)": ("mvo", "fast"), "GS OpenCV USAC_MAGSAC": ("gs", "fast"),
           "RS (ours)": ("rs", "fast")}  # fmt: skip
PAPER_MODE_LABEL = "RS paper-mode"


@dataclass
class TrialRecord:
    """One method on one frame pair."""

    method: str
    level: int
    noise: str
    trial: int
    ok: bool
    rot_err_deg: float
    trans_err_m: float
    inlier_ratio: float
    mid_rot_err_deg: float
    mid_tdir_err_deg: float
    w_err_deg_s: float  # mean over both frames of |w_est - w_gt|
    v_err_m_s: float  # mean over both frames of |v_est - v_gt| (estimate given GT scale)
    time_ms: float


def _noise(rng: np.random.Generator, kind: str, shape) -> np.ndarray:
    if kind == "gaussian":
        return rng.normal(0.0, NOISE_SIGMA_PX, shape)
    if kind == "laplacian":  # Laplace(b) has std b*sqrt(2)
        return rng.laplace(0.0, NOISE_SIGMA_PX / np.sqrt(2.0), shape)
    return np.zeros(shape)


def evaluate(pair: paper_scene.FramePair, res, method: str, level: int, noise: str,
             trial: int) -> TrialRecord:
    """The paper's metrics of one estimate (nan where the estimator returned ``ok=False``)."""
    nan = float("nan")
    if not res.ok:
        return TrialRecord(method, level, noise, trial, False, nan, nan, res.inlier_ratio, nan,
                           nan, nan, nan, res.time_s * 1e3)
    scale = float(np.linalg.norm(pair.t))
    t_est = res.t * scale
    dR = pair.R @ res.R.T  # dT = T_gt T_est^-1
    dt = pair.t - dR @ t_est
    mid = (pair.height - 1) / 2.0
    R_m, t_m = pair.pose_at_middle_row()
    R_me, t_me, _ = pose_at_row(res.R, t_est, res.w_prev, res.v_prev * scale, res.w_curr,
                                res.v_curr * scale, mid, pair.line_delay)
    w_err = 0.5 * (np.linalg.norm(res.w_prev - pair.w_prev)
                   + np.linalg.norm(res.w_curr - pair.w_curr))  # fmt: skip
    v_err = 0.5 * (np.linalg.norm(res.v_prev * scale - pair.v_prev)
                   + np.linalg.norm(res.v_curr * scale - pair.v_curr))  # fmt: skip
    return TrialRecord(
        method, level, noise, trial, True, float(rotation_angle_deg(dR)),
        float(np.linalg.norm(dt)), res.inlier_ratio, float(rotation_angle_deg(R_m @ R_me.T)),
        angle_between_deg(t_m, t_me), float(np.degrees(w_err)), float(v_err), res.time_s * 1e3,
    )  # fmt: skip


def run(levels, noises, trials: int, seed: int, paper_mode: bool,
        progress: bool = True) -> list[TrialRecord]:
    """All trials; every method sees the same correspondences."""
    scene = paper_scene.PaperScene(seed)
    methods = dict(METHODS)
    if paper_mode:
        methods[PAPER_MODE_LABEL] = ("rs", "paper")
    total = len(levels) * len(noises) * trials
    bar = None
    if progress:
        from tqdm import tqdm

        bar = tqdm(total=total, desc="rsvo_bench", unit="pair", file=sys.stderr)
    records = []
    for li, level in enumerate(levels):
        for ni, noise in enumerate(noises):
            rng = np.random.default_rng([seed, li, ni])
            for trial in range(trials):
                pair = scene.frame_pair(rng, level)
                nz = _noise(rng, noise, (2,) + pair.pts_prev.shape)
                pts_prev, pts_curr = pair.pts_prev + nz[0], pair.pts_curr + nz[1]
                for label, (model, mode) in methods.items():
                    res = estimate_relative_pose(pts_prev, pts_curr, pair.K, pair.line_delay,
                                                 model=model, seed=trial, mode=mode)
                    records.append(evaluate(pair, res, label, level, noise, trial))
                if bar is not None:
                    bar.update(1)
    if bar is not None:
        bar.close()
    return records


def summarize(records: list[TrialRecord]) -> dict:
    """Means, standard deviations and medians per (noise, method, level)."""
    out: dict = {}
    for r in records:
        out.setdefault(r.noise, {}).setdefault(r.method, {}).setdefault(r.level, []).append(r)
    summary: dict = {}
    for noise, by_method in out.items():
        for method, by_level in by_method.items():
            for level, rs in sorted(by_level.items()):
                def stat(field, rs=rs):
                    v = np.array([getattr(r, field) for r in rs], float)
                    v = v[np.isfinite(v)]
                    if not len(v):
                        return {"mean": None, "std": None, "median": None}
                    return {"mean": float(v.mean()), "std": float(v.std()),
                            "median": float(np.median(v))}  # fmt: skip

                summary.setdefault(noise, {}).setdefault(method, {})[str(level)] = {
                    "trials": len(rs),
                    "failed": int(sum(not r.ok for r in rs)),
                    **{f: stat(f) for f in ("rot_err_deg", "trans_err_m", "inlier_ratio",
                                            "mid_rot_err_deg", "mid_tdir_err_deg",
                                            "w_err_deg_s", "v_err_m_s", "time_ms")},
                }  # fmt: skip
    return summary


# issue 14's speed target for the RS estimator: a median per pair over the whole bench
RS_TIME_TARGET_MS = 12.0


def pair_times(records: list[TrialRecord]) -> dict:
    """Each method's median time per pair over every pair of the run (all levels and noise
    types; issue 14's figure), with the number of pairs, and the RS estimator's median against
    OpenCV's USAC_MAGSAC's in the same run (None without both)."""
    by_method: dict = {}
    for r in records:
        if np.isfinite(r.time_ms):
            by_method.setdefault(r.method, []).append(r.time_ms)
    out = {"median_ms": {m: float(np.median(t)) for m, t in by_method.items()},
           "pairs": {m: len(t) for m, t in by_method.items()},
           "target_ms": RS_TIME_TARGET_MS}
    rs, gs = out["median_ms"].get("RS (ours)"), out["median_ms"].get("GS OpenCV USAC_MAGSAC")
    out["rs_over_magsac"] = rs / gs if rs is not None and gs else None
    return out


def format_pair_times(times: dict) -> str:
    """One line: every method's median per pair over the run, and the RS / MAGSAC ratio."""
    parts = [f"{m} {t:.2f} ms" for m, t in times["median_ms"].items()]
    n = max(times["pairs"].values(), default=0)
    line = f"Time per pair over all {n} pairs, median: " + ", ".join(parts)
    rs, ratio = times["median_ms"].get("RS (ours)"), times["rs_over_magsac"]
    if ratio is not None:
        line += f" (RS / MAGSAC {ratio:.2f} in this run)"
    if rs is not None:
        met = "met" if rs <= times["target_ms"] else "not met"
        line += f"; the RS target of {times['target_ms']:g} ms per pair: {met}"
    return line


def _fmt(x, spec=".3f"):
    return "   -  " if x is None else format(x, spec)


def format_table(summary: dict, levels) -> str:
    """The paper's Table 1 layout: our means beside the paper's printed ones."""
    lines = []
    head = "".join(f"{'Lev ' + str(lv):>9}" for lv in levels)
    for noise in NOISE_TYPES:
        if noise not in summary:
            continue
        lines.append(f"\n== {noise} noise ==".replace("none noise", "noise-free"))
        lines.append(f"{'':34}{head}")
        for metric, label, scale, spec in (("rot_err_deg", "Rotation mean (deg)", 1, ".3f"),
                                           ("trans_err_m", "Translation mean (m)", 1, ".3f"),
                                           ("inlier_ratio", "Inlier ratio (%)", 100, ".1f"),
                                           ("mid_rot_err_deg", "Mid-row rotation (deg)", 1,
                                            ".3f"),
                                           ("time_ms", "Time per pair, median (ms)", 1,
                                            ".1f")):  # fmt: skip
            lines.append(label)
            for method, by_level in summary[noise].items():
                key = "median" if metric == "time_ms" else "mean"
                vals = []
                for lv in levels:
                    v = by_level.get(str(lv), {}).get(metric, {}).get(key)
                    vals.append(None if v is None else v * scale)
                lines.append(f"  {method:<32}" + "".join(f"{_fmt(v, spec):>9}" for v in vals))
            paper_key = {"rot_err_deg": "rot", "trans_err_m": "trans",
                         "inlier_ratio": "inlier"}.get(metric)  # fmt: skip
            if paper_key:
                for pm in ("MVO", "MRSVO"):
                    vals = [PAPER_TABLE1[noise][pm][paper_key][lv - 1] for lv in levels]
                    lines.append(f"  {'paper ' + pm:<32}"
                                 + "".join(f"{_fmt(v, spec):>9}" for v in vals))  # fmt: skip
    return "\n".join(lines)


# the README's Table 1: (metric, label, scale, format, methods); "paper MRSVO" is the paper's
MARKDOWN_ROWS = (
    ("rot_err_deg", "rotation (deg)", 1, ".3f",
     ("MVO (ours)", "GS OpenCV USAC_MAGSAC", "RS (ours)", "paper MRSVO")),
    ("trans_err_m", "translation (m)", 1, ".3f",
     ("MVO (ours)", "GS OpenCV USAC_MAGSAC", "RS (ours)", "paper MRSVO")),
    ("inlier_ratio", "inlier ratio (%)", 100, ".1f", ("RS (ours)", "paper MRSVO")),
    ("time_ms", "time / pair, median (ms)", 1, ".1f", ("RS (ours)", "GS OpenCV USAC_MAGSAC")),
)  # fmt: skip
NOISE_LABELS = {"none": "none", "gaussian": "Gaussian 1 px", "laplacian": "Laplacian 1 px"}


def format_markdown(summary: dict, levels) -> str:
    """The README's Table 1 (means; times as medians) as a markdown table: our methods and
    the paper's MRSVO per noise type and metric, one column per level."""
    lines = ["| noise | metric | method | " + " | ".join(f"L{lv}" for lv in levels) + " |",
             "|---|---|---|" + "---|" * len(levels)]
    for noise in NOISE_TYPES:
        if noise not in summary:
            continue
        first_metric = True
        for metric, label, scale, spec, methods in MARKDOWN_ROWS:
            for i, method in enumerate(methods):
                if method.startswith("paper "):
                    key = {"rot_err_deg": "rot", "trans_err_m": "trans",
                           "inlier_ratio": "inlier"}[metric]  # fmt: skip
                    vals = [PAPER_TABLE1[noise][method[6:]][key][lv - 1] for lv in levels]
                else:
                    stat = "median" if metric == "time_ms" else "mean"
                    by_level = summary[noise].get(method, {})
                    vals = [by_level.get(str(lv), {}).get(metric, {}).get(stat) for lv in levels]
                    vals = [None if v is None else v * scale for v in vals]
                name = f"**{method}**" if method == "RS (ours)" else method
                cells = " | ".join("-" if v is None else format(v, spec) for v in vals)
                lines.append(f"| {NOISE_LABELS[noise] if first_metric else ''} | "
                             f"{label if i == 0 else ''} | {name} | {cells} |")
                first_metric = False
    return "\n".join(lines)


def box_plot(records: list[TrialRecord], levels, path: Path) -> None:
    """Box plots like the paper's Fig. 4: rotation and translation error per level, one panel
    per noise type, MVO in red and our RS estimator in black (OpenCV GS in blue)."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    noises = [n for n in NOISE_TYPES if any(r.noise == n for r in records)]
    methods = [("MVO (ours)", "tab:red"), ("GS OpenCV USAC_MAGSAC", "tab:blue"),
               ("RS (ours)", "k")]
    if any(r.method == PAPER_MODE_LABEL for r in records):
        methods.append((PAPER_MODE_LABEL, "tab:gray"))
    fig, axes = plt.subplots(2, len(noises), figsize=(5.2 * len(noises), 7.5), squeeze=False)
    width = 0.8 / len(methods)
    for col, noise in enumerate(noises):
        for row, (field, ylabel) in enumerate((("rot_err_deg", "rotation error (deg)"),
                                               ("trans_err_m", "translation error (m)"))):
            ax = axes[row, col]
            for mi, (method, color) in enumerate(methods):
                data = []
                for lv in levels:
                    v = np.array([getattr(r, field) for r in records
                                  if r.noise == noise and r.method == method and r.level == lv])
                    data.append(v[np.isfinite(v)] if len(v) else np.array([np.nan]))
                pos = np.arange(len(levels)) + (mi - (len(methods) - 1) / 2) * width
                ax.boxplot(data, positions=pos, widths=width * 0.9, showfliers=True,
                           patch_artist=False, boxprops={"color": color},
                           medianprops={"color": color}, whiskerprops={"color": color},
                           capprops={"color": color},
                           flierprops={"markeredgecolor": color, "markersize": 3})
                ax.plot([], [], color=color, label=method)
            ax.set_xticks(np.arange(len(levels)), [f"Lev {lv}" for lv in levels])
            ax.set_yscale("symlog", linthresh=0.1 if field == "rot_err_deg" else 0.01)
            ax.set_ylim(bottom=0.0)
            ax.set_ylabel(ylabel)
            ax.grid(True, axis="y", alpha=0.3)
            if row == 0:
                ax.set_title("noise-free" if noise == "none" else f"{noise} noise (1 px)")
    axes[0, 0].legend(loc="upper left", fontsize=8)
    fig.suptitle("rsvo_bench: two-view relative pose under rolling-shutter distortion "
                 "(paper Sec. 7.1)")  # fmt: skip
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)


def build_parser() -> argparse.ArgumentParser:
    p = argparse.ArgumentParser(
        prog="rsvo_bench",
        description="Reproduce the synthetic experiment of Lee & Yoon (Sec. 7.1, Table 1): "
        "MVO, OpenCV's 5-point GS and our RS estimator on the same RS correspondences.",
    )
    p.add_argument("--output", "-o", type=Path, default=Path("results/bench"),
                   help="directory for bench.json and bench_boxplot.png (default: %(default)s)")
    p.add_argument("--trials", type=int, default=None,
                   help=f"Monte Carlo trials per level and noise type "
                        f"(default {DEFAULT_TRIALS}; {QUICK_TRIALS} with --quick)")
    p.add_argument("--levels", type=int, nargs="+", default=list(LEVELS), choices=LEVELS,
                   metavar="L", help="RS distortion levels 1-6 (default: all)")
    p.add_argument("--noise", nargs="+", default=list(NOISE_TYPES), choices=NOISE_TYPES,
                   help="noise types (default: all)")
    p.add_argument("--quick", action="store_true",
                   help=f"{QUICK_TRIALS} trials per cell: a smoke run for CI, not for numbers")
    p.add_argument("--paper-mode", action="store_true",
                   help="also run the paper-faithful RS mode (Algorithm 1: 500 LM hypotheses)")
    p.add_argument("--seed", type=int, default=0, help="scene and trial seed (default 0)")
    p.add_argument("--no-progress", action="store_true", help="no progress bar")
    real = p.add_argument_group("real image pairs (instead of the synthetic experiment)")
    real.add_argument("--real", type=Path, default=None, metavar="DIR",
                      help="evaluate every model on the RS pairs with GS twins in DIR (layout "
                           "of data/realdata/bsrsc: */rs_0.png, rs_1.png, gs_0_m.png, "
                           "gs_1_m.png); writes real.json and real_pairs.png")
    real.add_argument("--realistic", action="store_true",
                      help="evaluate every model on realistic synthetic pairs (smooth motion, "
                           "readout = frame interval, lens, KLT noise): the tuning seeds and "
                           "the held-out seeds; --trials limits the pairs per group")
    real.add_argument("--readout", type=_readout, default=realpairs.DEFAULT_READOUT,
                      metavar="R|auto", help="readout time in frame intervals (default "
                                             "%(default)s: the BS-RSC code's assumption); "
                                             "auto: also estimate it from the RS tracks alone "
                                             "and report the unrolling with it (the evaluation "
                                             "keeps the default)")
    real.add_argument("--focal", type=float, default=None, metavar="PX",
                      help="focal length in pixels (default: the image width)")
    return p


def main(argv: list[str] | None = None) -> int:
    args = build_parser().parse_args(argv)
    trials = args.trials if args.trials is not None else (
        QUICK_TRIALS if args.quick else DEFAULT_TRIALS)  # fmt: skip
    if trials < 1:
        print("rsvo_bench: --trials must be at least 1", file=sys.stderr)
        return 2
    if args.real is not None:
        return _main_real(args)
    if args.realistic:
        report = realpairs.run_realistic(args.output, args.trials, args.seed, args.readout)
        for name, group in report["groups"].items():
            print(f"\n== realistic synthetic pairs, {name} seeds {group['seeds'][0]}-"
                  f"{group['seeds'][1]} ==\n{group['table']}")
            _print_auto(group.get("readout_auto"), f"{name} seeds")
        print(f"\nwrote {args.output / 'realistic.json'}")
        return 0
    levels = sorted(set(args.levels))
    t0 = time.perf_counter()
    records = run(levels, args.noise, trials, args.seed, args.paper_mode,
                  progress=not args.no_progress)
    summary = summarize(records)
    times = pair_times(records)
    args.output.mkdir(parents=True, exist_ok=True)
    meta = {
        "command": "rsvo_bench " + " ".join(sys.argv[1:] if argv is None else argv),
        "trials_per_cell": trials, "levels": levels, "noise": args.noise, "seed": args.seed,
        "image": [paper_scene.IMAGE_WIDTH, paper_scene.IMAGE_HEIGHT],
        "focal_px": paper_scene.FOCAL_PX, "pixel_pitch_assumed_um": 5.0,
        "line_delay_s": paper_scene.LINE_DELAY, "max_features": paper_scene.MAX_FEATURES,
        "rs_levels_m_s_deg_s": paper_scene.RS_LEVELS, "noise_sigma_px": NOISE_SIGMA_PX,
        "wall_time_s": time.perf_counter() - t0,
    }  # fmt: skip
    with open(args.output / "bench.json", "w") as f:
        json.dump({"meta": meta, "summary": summary, "pair_times": times,
                   "paper_table1": PAPER_TABLE1,
                   "records": [asdict(r) for r in records]}, f, indent=1)  # fmt: skip
    (args.output / "bench.md").write_text(format_markdown(summary, levels) + "\n\n"
                                          + format_pair_times(times) + "\n")
    box_plot(records, levels, args.output / "bench_boxplot.png")
    print(format_table(summary, levels))
    print("\n" + format_pair_times(times))
    print(f"\n{len(records)} estimates in {meta['wall_time_s']:.1f} s; wrote "
          f"{args.output / 'bench.json'}, bench.md (the README's table) and "
          f"{args.output / 'bench_boxplot.png'}")
    return 0


def _readout(text: str) -> float | str:
    """``--readout``: ``auto`` or a number of frame intervals >= 0."""
    if text == "auto":
        return text
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected 'auto' or a number, got {text!r}") from None
    if not (np.isfinite(value) and value >= 0):
        raise argparse.ArgumentTypeError(f"must be finite and >= 0, got {text!r}")
    return value


def _print_auto(auto: dict | None, label: str) -> None:
    if auto is None:
        return
    per = ", ".join(f"{k} {'-' if v is None else format(v, '.2f')}"
                    for k, v in auto["per_pair"].items())
    un = auto["unroll_px_median_estimate"]
    print(f"\n{label}: readout from the RS tracks alone: {auto['status']} ({auto['reason']}); "
          f"per pair: {per}. Stream-mode unrolling, median: "
          f"{'-' if un is None else format(un, '.2f')} px with the estimate, "
          f"{auto['unroll_px_median_assumed']:.2f} px with {auto['assumed_readout']:g} frame "
          f"intervals, {auto['nothing_px_median']:.2f} px doing nothing")


def _main_real(args) -> int:
    try:
        report = realpairs.run(args.real, args.output, readout=args.readout, focal=args.focal,
                               seed=args.seed)
    except (realpairs.RealDataError, ValueError) as exc:
        print(f"rsvo_bench: {exc}", file=sys.stderr)
        return 2
    print(report["table"])
    _print_auto(report["readout_auto"], "real pairs")
    print(f"\n{len(report['pairs'])} real pairs, readout "
          f"{report['readout_frame_intervals']:g} frame intervals; "
          f"wrote {args.output / 'real.json'} and {args.output / 'real_pairs.png'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
