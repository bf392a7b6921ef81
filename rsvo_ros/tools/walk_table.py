"""Issue 13's walk targets on fresh hand-held walks: under 3 % of the path, the scale kept.

    python -m rsvo_ros.tools.walk_table OUT --seeds 1600-1615 [--frames 300] [--severity 0.7]
        [--jobs 2] [--window-option NAME=VALUE ...] [--decimation D] [--stamp-jitter S]
        [--against OTHER_OUT]

For each seed a 30 Hz hand-held walk is written (``rsvo_synth --motion walk --severity 0.7
--frames 300 --seed N``: every walk of 8 s or more stops and looks 40 deg left and right) or
reused from OUT, and replayed with the defaults (RS model, window backend, the bag's line
delay), the ``--window-option`` / ``--decimation`` settings on top (for A/B runs). Per walk:
ATE after Sim(3) and as a share of the true path, the run's Sim(3) scale against its first 60
frames' (``summary.json`` ``accuracy.scale_drift.ratio``; within 10 % is the target), frames
with a pose, map re-finds, and the estimate's size against the truth second by second (the
Sim(3) scale of each second's positions, relative to the first 60 frames': where a walk loses
or gains its scale). Writes ``walks.md``, ``walks.json`` and ``walk_scale.png`` into OUT.
Use seeds nobody has tuned on for a verdict: the README says which were looked at.
``--against`` compares the walks seed by seed with an earlier table's (an A/B run; the ATE
of each walk in both, ``walk_against.png``); the same
walks with ``--stamp-jitter 0.001`` against the plain ones show how far they move without a
change of method: the floor an A/B difference has to clear.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

from rsvo_ros.odometry.pipeline import PipelineOptions
from rsvo_ros.odometry.tracker import MAX_DECIMATION, check_decimation
from rsvo_ros.sim.synth import SynthConfig
from rsvo_ros.tools.compare import read_ground_truth, read_tum
from rsvo_ros.tools.rate_table import fmt, gmean, run_cases
from rsvo_ros.tools.replay import (
    SCALE_CHECK_FRAMES,
    ReplayConfig,
    replay,
    set_window_options,
    window_option_arg,
)
from rsvo_ros.tools.synth_bag import check_stamp_jitter, write_bag

PATH_SHARE_TARGET = 0.03  # issue 13: every walk under 3 % of its path
SCALE_TARGET = 0.10  # ... its whole-run scale within 10 % of its first 60 frames'
POSED_TARGET = 0.98  # ... a pose or a counted hold for >= 98 % of the frames
SEGMENT_S = 1.0  # the size-against-truth series: one value per this many seconds
SEGMENT_MIN_PATH_M = 0.05  # a second in which the truth moved less is left out (a stop)


def parse_seeds(text: str) -> list[int]:
    """``"1600-1615"``, ``"7"`` or ``"3,5,9-11"`` as a list of seeds; ``ValueError`` otherwise."""
    seeds: list[int] = []
    for part in text.split(","):
        lo, sep, hi = part.strip().partition("-")
        try:
            a, b = int(lo), int(hi) if sep else int(lo)
        except ValueError:
            raise ValueError(f"--seeds takes seeds and ranges like 1600-1615 or 3,5,9-11, "
                             f"got {text!r}") from None
        if a < 0 or b < a:
            raise ValueError(f"--seeds: {part.strip()!r} is not a range of seeds >= 0")
        seeds.extend(range(a, b + 1))
    return list(dict.fromkeys(seeds))


def sim3_scale(source: np.ndarray, target: np.ndarray) -> float:
    """The scale ``s`` of the least-squares similarity ``target ~ s R source + t`` (evo's
    Umeyama alignment, as the replay's ATE) of (M, 3) positions; nan where ``source`` does not
    spread."""
    from evo.core.geometry import GeometryException, umeyama_alignment

    try:
        return float(umeyama_alignment(source.T, target.T, with_scale=True)[2])
    except GeometryException:
        return float("nan")


def size_by_second(stamps_s: np.ndarray, gt_xyz: np.ndarray,
                   est_xyz: np.ndarray) -> list[tuple[float, float]]:  # fmt: skip
    """``(t, size)``: for each ``SEGMENT_S`` of the run, the Sim(3) scale of the estimate's
    positions against the truth's (map units per metre) over the first ``SCALE_CHECK_FRAMES``
    frames' (1: the start's size; 0.5: the estimate is half as large there). Seconds in which
    the truth moved less than ``SEGMENT_MIN_PATH_M`` are left out; empty without a start."""
    t = np.asarray(stamps_s, float)
    n0 = min(SCALE_CHECK_FRAMES, len(t))
    if n0 < 3:
        return []
    start = sim3_scale(gt_xyz[:n0], est_xyz[:n0])
    if not np.isfinite(start) or start <= 0:
        return []
    out = []
    for t0 in np.arange(t[0], t[-1], SEGMENT_S):
        k = (t >= t0) & (t < t0 + SEGMENT_S)
        if k.sum() < 3:
            continue
        path = float(np.linalg.norm(np.diff(gt_xyz[k], axis=0), axis=1).sum())
        if path < SEGMENT_MIN_PATH_M:
            continue
        s = sim3_scale(gt_xyz[k], est_xyz[k])
        if np.isfinite(s):
            out.append((float(t0 - t[0]), s / start))
    return out


def run_walk(out: Path, seed: int, frames: int, severity: float,
             window_options: list[tuple[str, float]], decimation: int,
             stamp_jitter_s: float = 0.0) -> dict:  # fmt: skip
    """Write (or reuse) one walk's bag, replay it and return its row (with ``error`` and no
    figures where the bag cannot be written or replayed: the other walks go on).
    ``stamp_jitter_s`` > 0: the bag's stamps late by up to that (``rsvo_synth
    --stamp-jitter``), in a bag of its own name."""
    jitter = f"_jitter{stamp_jitter_s:g}" if stamp_jitter_s > 0 else ""
    bag = out / "bags" / f"walk_sev{severity:g}_{frames}f_seed{seed}{jitter}"
    try:
        if not (bag / "metadata.yaml").exists():
            write_bag(bag, SynthConfig(frames=frames, motion="walk", severity=severity,
                                       seed=seed), overwrite=True, progress=False,
                      stamp_jitter_s=stamp_jitter_s)  # fmt: skip
        options = PipelineOptions()
        set_window_options(options, window_options)
        options.tracker.decimation = decimation
        run = out / "replays" / bag.name
        s = replay(ReplayConfig(bag, run, overwrite=True, progress=False, options=options))
    except Exception as exc:  # noqa: BLE001 - one walk's failure is its row, not the table's
        return {"seed": seed, "error": f"{type(exc).__name__}: {exc}", "frames": 0, "posed": 0,
                "held": 0, "path_m": None, "ate_m": None, "ate_share": None,
                "scale_ratio": None, "rpe_rot_deg": None, "map_refound": 0,
                "size_by_second": []}
    acc = s.get("accuracy") or {}
    gt, est = read_ground_truth(bag), read_tum(run / "trajectory.tum")
    stamps = [k for k in sorted(est) if k in gt]
    g = np.array([gt[k][:3, 3] for k in stamps]).reshape(-1, 3)
    e = np.array([est[k][:3, 3] for k in stamps]).reshape(-1, 3)
    path = float(np.linalg.norm(np.diff(g, axis=0), axis=1).sum()) if len(g) > 1 else 0.0
    ate = (acc.get("ate_m") or {}).get("rmse")
    return {"seed": seed, "frames": s["frames_in"], "posed": s["frames_posed"],
            "held": s["frames_held"], "path_m": path, "ate_m": ate,
            "ate_share": None if ate is None or path <= 0 else ate / path,
            "scale_ratio": (acc.get("scale_drift") or {}).get("ratio"),
            "rpe_rot_deg": (acc.get("rpe_rot_deg") or {}).get("rmse"),
            "map_refound": s.get("map_refound", 0),
            "size_by_second": size_by_second(np.array(stamps) * 1e-9, g, e)}


def verdicts(row: dict) -> dict[str, bool | None]:
    """The row against issue 13's walk targets (None where it cannot be judged)."""
    share, ratio = row["ate_share"], row["scale_ratio"]
    return {"path": None if share is None else share < PATH_SHARE_TARGET,
            "scale": None if ratio is None else abs(ratio - 1.0) <= SCALE_TARGET,
            "posed": None if "error" in row
            else (row["posed"] + row["held"]) >= POSED_TARGET * row["frames"]}


def table(rows: list[dict]) -> str:
    lines = ["| seed | ATE | share of the path | scale against the first 60 frames | "
             "size by second (min / max) | RPE rotation per frame | frames with a pose "
             "(held) | map re-found |", "|---" * 8 + "|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['seed']} | not replayed: {r['error']} |" + " |" * 6)
            continue
        sizes = [v for _, v in r["size_by_second"]]
        lines.append(
            f"| {r['seed']} | {fmt(r['ate_m'], '.3f')} m | "
            f"{fmt(None if r['ate_share'] is None else 100 * r['ate_share'], '.1f')} % | "
            f"{fmt(r['scale_ratio'], '.3f')} | "
            + (f"{min(sizes):.2f} / {max(sizes):.2f}" if sizes else "-")
            + f" | {fmt(r['rpe_rot_deg'], '.3f')} deg | {r['posed']} ({r['held']}) of "
            f"{r['frames']} | {r['map_refound']} |")
    return "\n".join(lines)


def summary(rows: list[dict]) -> str:
    v = [verdicts(r) for r in rows]
    n = len(rows)

    def count(key):
        return f"{sum(x[key] is True for x in v)} of {n}"

    failed = [r["seed"] for r in rows if "error" in r]
    return (f"{n} walks: under {100 * PATH_SHARE_TARGET:g} % of the path on {count('path')}; "
            f"scale within {100 * SCALE_TARGET:g} % of the first {SCALE_CHECK_FRAMES} frames' on "
            f"{count('scale')}; a pose or a hold for >= {100 * POSED_TARGET:g} % of the frames "
            f"on {count('posed')}; ATE {fmt(gmean(r['ate_m'] for r in rows), '.3f')} m in "
            f"geometric mean" + (f"; not replayed: seeds {failed}" if failed else ""))


# what a row needs to be compared (its ATE and the targets' verdicts)
ROW_KEYS = ("seed", "ate_m", "ate_share", "scale_ratio", "frames", "posed", "held")


def read_rows(path: Path) -> list[dict]:
    """The rows of an earlier walk table (its ``walks.json``, or the directory holding it);
    ``ValueError`` naming the file where it is missing or not a walk table's."""
    path = path / "walks.json" if path.is_dir() else path
    try:
        rows = json.loads(path.read_text())["rows"]
        missing = {k for r in rows for k in ROW_KEYS if k not in r}
        if missing:
            raise KeyError(", ".join(sorted(missing)))
    except FileNotFoundError:
        raise ValueError(f"--against: no walk table at {path}") from None
    except OSError as exc:
        raise ValueError(f"--against: cannot read {path}: {exc}") from None
    except (json.JSONDecodeError, KeyError, TypeError) as exc:
        raise ValueError(f"--against: {path} is not a walk table's walks.json ({exc})") from None
    return rows


def compare(rows: list[dict], base: list[dict]) -> dict:
    """Each seed replayed in both tables: this table's ATE over the other's (``ratios``, by
    seed), their geometric mean, how many are the same to 1e-9 m or within 10 %, and both
    tables' target counts over those seeds (an A/B verdict; the other is the baseline)."""
    old = {r["seed"]: r for r in base if r.get("ate_m")}
    both = [(r, old[r["seed"]]) for r in rows if r.get("ate_m") and r["seed"] in old]
    ratios = {r["seed"]: r["ate_m"] / b["ate_m"] for r, b in both}

    def counts(sel):
        v = [verdicts(r) for r in sel]
        return {k: sum(x[k] is True for x in v) for k in ("path", "scale")}

    return {"seeds": len(both), "ratios": ratios,
            "ratio_gmean": gmean(ratios.values()) if ratios else None,
            "same": sum(abs(r["ate_m"] - b["ate_m"]) <= 1e-9 for r, b in both),
            "within_10_percent": sum(abs(q - 1.0) <= 0.1 for q in ratios.values()),
            "this": counts([r for r, _ in both]), "base": counts([b for _, b in both])}


def format_comparison(c: dict, base_name: str) -> str:
    """:func:`compare`'s result as one line, the other table named ``base_name``."""
    if not c["seeds"]:
        return f"Against {base_name}: no seed replayed in both tables."
    q = c["ratios"]
    lo, hi = min(q, key=q.get), max(q, key=q.get)
    return (f"Against {base_name} ({c['seeds']} walks in both): ATE {c['ratio_gmean']:.3f}x in "
            f"geometric mean (per walk {q[lo]:.2f}x, seed {lo}, to {q[hi]:.2f}x, seed {hi}); "
            f"{c['same']} the same, {c['within_10_percent']} within 10 %; under "
            f"{100 * PATH_SHARE_TARGET:g} % of the path on {c['this']['path']} against "
            f"{c['base']['path']}, scale within {100 * SCALE_TARGET:g} % on "
            f"{c['this']['scale']} against {c['base']['scale']}")


def plot_against(path: Path, rows: list[dict], base: list[dict], c: dict,
                 base_name: str) -> None:  # fmt: skip
    """Each walk's ATE in this table against the other's (log-log), the line of equal ATE and
    a band of +-10 % around it; a walk that misses the path target in either table is drawn
    as a hollow red circle."""
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    this = {r["seed"]: r for r in rows}
    old = {r["seed"]: r for r in base}
    seeds = [int(s) for s in c["ratios"]]
    x = np.array([old[s]["ate_m"] for s in seeds])
    y = np.array([this[s]["ate_m"] for s in seeds])
    fig, ax = plt.subplots(figsize=(5.2, 5.0))
    if len(seeds):
        lo, hi = 0.8 * min(x.min(), y.min()), 1.25 * max(x.max(), y.max())
        d = np.array([lo, hi])
        ax.fill_between(d, d / 1.1, d * 1.1, color="0.9", label="within 10 %")
        ax.plot(d, d, "k-", lw=0.8)
        missed = np.array([verdicts(this[s])["path"] is False or verdicts(old[s])["path"]
                           is False for s in seeds])  # fmt: skip
        ax.scatter(x[~missed], y[~missed], s=22, color="tab:blue", zorder=3)
        ax.scatter(x[missed], y[missed], s=40, facecolors="none", edgecolors="tab:red",
                   zorder=3, label="over 3 % of the path in either")
        for s, xi, yi in zip(seeds, x, y, strict=True):
            ax.annotate(str(s), (xi, yi), fontsize=6, xytext=(3, 2),
                        textcoords="offset points")
        ax.set_xlim(lo, hi)
        ax.set_ylim(lo, hi)
        ax.set_xscale("log")
        ax.set_yscale("log")
        plain = matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}")
        for axis in (ax.xaxis, ax.yaxis):
            axis.set_major_formatter(plain)
            axis.set_minor_locator(matplotlib.ticker.LogLocator(subs=(2.0, 3.0, 5.0)))
            axis.set_minor_formatter(plain)
        ax.legend(fontsize=7, loc="upper left")
        ax.set_title(f"ATE {c['ratio_gmean']:.3f}x in geometric mean over {len(seeds)} walks",
                     fontsize=9)
    else:
        ax.text(0.5, 0.5, "no walk in both tables", ha="center", transform=ax.transAxes)
    ax.set_xlabel(f"ATE (m), {base_name}", fontsize=8)
    ax.set_ylabel("ATE (m), this table")
    ax.tick_params(labelsize=7, which="both")
    ax.grid(alpha=0.3, which="both")
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def plot(path: Path, rows: list[dict]) -> None:
    import matplotlib
    import matplotlib.ticker

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(9, 4.2))
    ax.axhspan(1 - SCALE_TARGET, 1 + SCALE_TARGET, color="0.9", label="within 10 %")
    for r in rows:
        if not r["size_by_second"]:
            continue
        t, v = np.array(r["size_by_second"]).T
        bad = verdicts(r)["scale"] is False or verdicts(r)["path"] is False
        ax.plot(t, v, "-o", ms=3, lw=1.6 if bad else 0.8, alpha=1.0 if bad else 0.5,
                label=f"seed {r['seed']}" if bad else None)
    ax.set_yscale("log")
    plain = matplotlib.ticker.FuncFormatter(lambda v, _: f"{v:g}")
    ax.yaxis.set_major_formatter(plain)
    ax.yaxis.set_minor_locator(matplotlib.ticker.LogLocator(subs=(0.5, 0.7, 1.5, 2.0, 3.0)))
    ax.yaxis.set_minor_formatter(plain)
    ax.set_xlabel("time (s)")
    ax.set_ylabel("estimate's size against the truth,\nrelative to the first 60 frames")
    ax.set_title("size second by second (thick: a walk that misses a target)", fontsize=9)
    ax.grid(alpha=0.3, which="both")
    ax.legend(fontsize=7, ncol=2)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def _describe(k: int, n: int, r: dict) -> str:
    """The progress line of the k-th of n walks."""
    if "error" in r:
        return f"[walk_table {k}/{n}] seed {r['seed']}: not replayed: {r['error']}"
    share = None if r["ate_share"] is None else 100 * r["ate_share"]
    return (f"[walk_table {k}/{n}] seed {r['seed']}: ATE {fmt(r['ate_m'], '.3f')} m "
            f"({fmt(share, '.1f')} % of the path), scale {fmt(r['scale_ratio'], '.3f')}")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m rsvo_ros.tools.walk_table", description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path)
    p.add_argument("--seeds", default="1600-1615", help="seeds and ranges (1600-1615)")
    p.add_argument("--frames", type=int, default=300)
    p.add_argument("--severity", type=float, default=0.7, help="shake (0.7)")
    p.add_argument("--jobs", type=int, default=1, help="walks replayed side by side (1)")
    p.add_argument("--window-option", type=window_option_arg, action="append", default=[],
                   metavar="NAME=VALUE", help="a numeric WindowOptions field (repeatable)")
    p.add_argument("--decimation", type=int, default=1,
                   help=f"track at 1/D of the resolution (1-{MAX_DECIMATION}; default 1)")
    p.add_argument("--stamp-jitter", type=float, default=0.0, metavar="S",
                   help="the walks' stamps late by a uniform 0-S seconds (rsvo_synth "
                        "--stamp-jitter: a live driver's stamps); the same walks once more "
                        "with it show how far single walks move under a change that is no "
                        "change of method (README, \"How far a walk moves\"; default 0)")
    p.add_argument("--against", type=Path, default=None, metavar="TABLE",
                   help="an earlier walk table (its OUT or walks.json) to compare with, seed "
                        "by seed: ATE ratios, their geometric mean, the target counts of both "
                        "(A/B runs; a run with --stamp-jitter against the plain one gives "
                        "the noise floor to judge them by)")
    args = p.parse_args(argv)
    try:
        seeds = parse_seeds(args.seeds)
        check_decimation(args.decimation, "--decimation")
        if args.frames < 2 * SCALE_CHECK_FRAMES:
            raise ValueError(f"--frames must be at least {2 * SCALE_CHECK_FRAMES} (the scale "
                             f"check compares the run with its first {SCALE_CHECK_FRAMES})")
        if args.jobs < 1 or not args.severity >= 0:
            raise ValueError("--jobs must be at least 1 and --severity at least 0")
        check_stamp_jitter(SynthConfig(motion="walk"), args.stamp_jitter)
        base = None if args.against is None else read_rows(args.against)
    except ValueError as exc:
        print(f"walk_table: {exc}", file=sys.stderr)
        return 2
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = [(args.out, seed, args.frames, args.severity, args.window_option, args.decimation,
             args.stamp_jitter) for seed in seeds]
    rows = run_cases(run_walk, jobs, args.jobs, _describe)
    meta = {"command": "python -m rsvo_ros.tools.walk_table " + " ".join(
        sys.argv[1:] if argv is None else argv), "rows": rows}
    text = summary(rows)
    if base is not None:
        meta["against"] = {"table": str(args.against), **compare(rows, base)}
        text += "\n\n" + format_comparison(meta["against"], str(args.against))
    (args.out / "walks.json").write_text(json.dumps(meta, indent=1))
    (args.out / "walks.md").write_text(table(rows) + "\n\n" + text + "\n")
    plot(args.out / "walk_scale.png", rows)
    written = "walks.json, walk_scale.png"
    if base is not None:
        plot_against(args.out / "walk_against.png", rows, base, meta["against"],
                     str(args.against))
        written += ", walk_against.png"
    print(text)
    print(f"wrote {args.out / 'walks.md'}, {written}")
    for r in rows:
        if "error" in r:
            print(f"walk_table: seed {r['seed']} not replayed: {r['error']}", file=sys.stderr)
    return 1 if any("error" in r for r in rows) else 0


if __name__ == "__main__":
    sys.exit(main())
