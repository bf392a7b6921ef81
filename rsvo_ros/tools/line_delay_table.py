"""The README's line-delay table: ``line_delay: auto`` on synthetic bags with known line delays.

    python -m rsvo_ros.tools.line_delay_table OUT [--frames 150] [--jobs 2]

For each case a bag is written (``rsvo_synth``) and replayed: with ``--line-delay auto
--two-pass`` (the first pass as the live node runs, and the offline second pass with its
estimate), with ``--line-delay auto`` in one pass (its frames before the first estimate are
processed again with it, and with later estimates away from it), with the true line delay and
with 0 (a global-shutter model of an RS camera). The "estimate" is the pipeline's after
the bag's 150 frames, as the node makes it (no re-runs; refined after 150 frames,
``PipelineOptions.line_delay_auto_refine_frames``; the one the second pass takes); beside it
the calibrator's own estimate that the refinement started from (over all its windows at frame
150, since the twenty-sixth session; before it, and the node's until the twenty-fifth session,
its last estimate, kept in the JSON as ``estimate_calibrator_last``), the one-pass replay's
(with the re-runs, refined too), and ``rsvo_calibrate``'s: the calibrator's last estimate
refined in a second pass over the whole bag
(``PipelineOptions.line_delay_refine``; the same frames here).
Columns: the true and the estimated line delay (with the bootstrap uncertainty), the relative
error, and the ATE of each replay. Seeds 0, 100 and 101 (walks) and 0 (vehicle, handheld) were
looked at while the method was chosen; the 200-series were held out until the spline velocities
and the refining schedule were compared on them (2026-11-23); the 300-series ("fresh") were
written after that choice, and no setting was changed for them; "fresh 2" (seeds 500-502) were
written when the two passes were added and run once with them. Writes ``line_delay.md`` (the
table and per-group counts against the issue's targets), ``line_delay.json`` and
``line_delay.png`` into OUT.
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
from rsvo_ros.tools.replay import ReplayConfig, replay, replay_two_pass
from rsvo_ros.tools.synth_bag import write_bag

CASES = [  # (group, motion, severity, seed, line delay s/row)
    *[("looked at", "walk", 1.0, 0, ld) for ld in (0.0, 2e-5, 5e-5, 1e-4)],
    ("looked at", "walk", 0.5, 100, 2e-5),
    ("looked at", "walk", 2.0, 101, 1e-4),
    ("looked at", "vehicle", 1.0, 0, 5e-5),
    ("looked at", "handheld", 1.0, 0, 1e-4),
    *[("held out", "walk", 1.0, seed, ld) for seed in (200, 201) for ld in (0.0, 2e-5, 5e-5,
                                                                          1e-4)],
    ("held out", "walk", 2.0, 202, 5e-5),
    ("held out", "vehicle", 1.0, 200, 5e-5),
    ("held out", "vehicle", 2.0, 201, 2e-5),
    ("held out", "handheld", 1.0, 200, 1e-4),
    # written after the spline velocities and the refining schedule were chosen
    *[("fresh", "walk", 1.0, seed, ld) for seed in (300, 301) for ld in (0.0, 3e-5, 7e-5)],
    ("fresh", "walk", 2.0, 302, 3e-5),
    ("fresh", "vehicle", 1.0, 300, 7e-5),
    ("fresh", "vehicle", 2.0, 301, 1e-4),
    ("fresh", "handheld", 1.0, 300, 5e-5),
    ("fresh", "handheld", 2.0, 301, 3e-5),
    # written when the two passes were added (2026-11-25), run once with them
    *[("fresh 2", "walk", 1.0, seed, ld) for seed in (500, 501) for ld in (4e-5, 9e-5)],
    ("fresh 2", "walk", 2.0, 502, 8e-5),
    ("fresh 2", "handheld", 1.0, 500, 8e-5),
    ("fresh 2", "vehicle", 2.0, 500, 6e-5),
]


def case_name(motion: str, severity: float, seed: int, line_delay: float) -> str:
    """A case's name (its bag's directory; the rows' ``case``)."""
    return f"{motion}_sev{severity:g}_seed{seed}_ld{line_delay * 1e6:g}us"


def run_case(out: Path, motion: str, severity: float, seed: int, line_delay: float,
             frames: int) -> dict:  # fmt: skip
    name = case_name(motion, severity, seed, line_delay)
    bag = out / name
    if not (bag / "metadata.yaml").exists():
        write_bag(bag, SynthConfig(frames=frames, motion=motion, severity=severity, seed=seed,
                                   line_delay=line_delay), overwrite=True, progress=False)
    row = {"case": name, "motion": motion, "severity": severity, "seed": seed,
           "line_delay_true_s": line_delay}

    def kept(summary: dict) -> dict:
        return {k: v for k, v in summary["line_delay_auto"].items()
                if k not in ("curve", "history", "reruns")}

    for label, ld in (("auto", None), ("true", line_delay), ("zero", 0.0)):
        opts = PipelineOptions(line_delay_auto=label == "auto")
        cfg = ReplayConfig(bag, out / f"{name}__{label}", line_delay=ld, overwrite=True,
                           progress=False, options=opts)  # fmt: skip
        s = replay(cfg)
        row[f"ate_{label}_m"] = s["accuracy"]["ate_m"]["rmse"]
        if label == "auto":  # one pass, the first frames re-run with the estimates
            row["estimate_rerun"] = kept(s)
            row["reruns"] = [[r["frames"], r["line_delay_s"]]
                             for r in s["line_delay_auto"]["reruns"]]
    # as the node runs (no re-runs; its estimate is the one rsvo_calibrate and the node give),
    # then the offline second pass with that estimate
    cfg = ReplayConfig(bag, out / f"{name}__two_pass", overwrite=True, progress=False,
                       options=PipelineOptions(line_delay_auto=True))  # fmt: skip
    s = replay_two_pass(cfg)
    row["ate_auto_node_m"] = s["two_pass"]["first_pass_ate_m"]
    row["ate_two_pass_m"] = s["accuracy"]["ate_m"]["rmse"]
    row["estimate"] = kept(s)
    row["line_delay_used_s"] = s["two_pass"]["first_pass_line_delay_s"]
    history = s["line_delay_auto"].get("history", [])
    row["history"] = [[h["frames"], h["line_delay_s"]] for h in history]
    # the calibrator's own estimates, before the pipeline refined them after 150 frames
    # (PipelineOptions.line_delay_auto_refine_frames): its last one (the node's and the
    # table's estimate before the twenty-fifth session; rsvo_calibrate's first pass ends with
    # it), and the one over all its windows at frame 150 that the refinement started from
    calibrator = [h for h in history if h["status"] != "refined" and h["line_delay_s"]
                  is not None]  # fmt: skip
    last = ({k: calibrator[-1][k] for k in ("line_delay_s", "std_s", "status", "reason")}
            if calibrator else dict(row["estimate"]))  # fmt: skip
    ref = row["refinement"] = s["line_delay_auto"].get("refinement")
    row["estimate_calibrator"] = row["estimate_calibrator_last"] = last
    if ref is not None and ref.get("first_line_delay_s") is not None:
        row["estimate_calibrator"] = {"line_delay_s": ref["first_line_delay_s"],
                                      "std_s": ref.get("first_std_s"), "status": "estimated",
                                      "reason": f"over {ref['first_windows']} windows"}
    # rsvo_calibrate's: the calibrator's last estimate refined in a second pass over the
    # whole bag (a zero one kept)
    first = last["line_delay_s"]
    row["estimate_refined"] = {"line_delay_s": first,
                               "std_s": last["std_s"],
                               "status": "first kept",
                               "reason": "no estimate" if first is None
                               else "a zero line delay (a global shutter) is kept"}
    if first:
        cfg = ReplayConfig(bag, out / f"{name}__refined", line_delay=first, overwrite=True,
                           progress=False, options=PipelineOptions(line_delay_refine=True))
        ref = replay(cfg)["line_delay_refined"]
        if ref["status"] == "refined":
            row["estimate_refined"] = {k: ref[k] for k in ("line_delay_s", "std_s", "status",
                                                             "reason")}  # fmt: skip
        else:
            row["estimate_refined"]["reason"] = ref["reason"]
    return row


def within(row: dict, key: str = "estimate") -> bool:
    """The issue's target for the row's estimate ``key`` (:func:`within_target`)."""
    return within_target(row[key]["line_delay_s"], row["line_delay_true_s"])


def within_target(estimate: float | None, true: float) -> bool:
    """The issue's target: within 10 % of the true line delay (2 us/row below 20 us/row); no
    estimate is a miss."""
    return estimate is not None and abs(estimate - true) <= (2e-6 if true < 2e-5
                                                             else 0.10 * true)


def near(key: str, rows: list[dict]) -> int:
    """How many of ``rows`` have the ATE ``key`` within 10 % of the true line delay's."""
    return sum(r[key] <= 1.10 * r["ate_true_m"] for r in rows)


def summary(rows: list[dict]) -> str:
    """Per group: estimates within the target, and ATE with auto within 10 % of the true
    line delay's, over the rolling-shutter cases."""
    out = []
    for group in dict.fromkeys(r["group"] for r in rows):
        rs = [r for r in rows if r["group"] == group and r["line_delay_true_s"] > 0]
        gs = [r for r in rows if r["group"] == group and r["line_delay_true_s"] == 0]
        zero = sum(within(r) for r in gs)
        reran = sum(within(r, "estimate_rerun") for r in rs)
        refined = sum(within(r, "estimate_refined") for r in rs)
        zero_refined = sum(within(r, "estimate_refined") for r in gs)
        first = sum(within(r, "estimate_calibrator") for r in rs)
        last = sum(within(r, "estimate_calibrator_last") for r in rs
                   if "estimate_calibrator_last" in r)  # fmt: skip
        out.append(f"- {group}: line delay within 10 % on {sum(within(r) for r in rs)} of "
                   f"{len(rs)} rolling-shutter bags (the calibrator's where the "
                   f"refinement started: {first}; its last estimate: {last}; with the "
                   f"re-runs: {reran}; "
                   f"rsvo_calibrate's, "
                   f"refined in a second pass: {refined}; global shutter {zero_refined} of "
                   f"{len(gs)}), ATE auto "
                   f"within 10 % of ATE true on {near('ate_auto_m', rs)} of {len(rs)} (as the "
                   f"node, without the re-runs: "
                   f"{near('ate_auto_node_m', rs)}; two passes: {near('ate_two_pass_m', rs)}); "
                   f"global shutter within 2 us/row on {zero} of {len(gs)}, its ATE auto "
                   f"within 10 % on {near('ate_auto_m', gs)} (as the node: "
                   f"{near('ate_auto_node_m', gs)})")
    return "\n".join(out)


def plot(path: Path, rows: list[dict]) -> None:
    """Left: estimate against truth per group; right: estimate / truth over the frames seen
    (the refining), rolling-shutter bags."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, (ax, bx) = plt.subplots(1, 2, figsize=(11, 4.2))
    top = 1e6 * max(r["line_delay_true_s"] for r in rows) * 1.3
    ax.fill_between([0, top], [0, 0.9 * top], [0, 1.1 * top], color="0.9", label="within 10 %")
    ax.plot([0, top], [0, top], "k-", lw=0.8)
    for (group, marker), colour in zip(
            (("looked at", "o"), ("held out", "s"), ("fresh", "^"), ("fresh 2", "v")),
            ("tab:gray", "tab:blue", "tab:red", "tab:green"), strict=True):  # fmt: skip
        grp = [r for r in rows if r["group"] == group and r["estimate"]["line_delay_s"]
               is not None]
        if not grp:
            continue
        ax.errorbar([1e6 * r["line_delay_true_s"] for r in grp],
                    [1e6 * r["estimate"]["line_delay_s"] for r in grp],
                    yerr=[1e6 * (r["estimate"]["std_s"] or 0.0) for r in grp], fmt=marker,
                    color=colour, label=group, ms=5, capsize=2)
        for r in grp:
            hist = [(f, ld) for f, ld in r.get("history", []) if ld is not None]
            if r["line_delay_true_s"] > 0 and hist:
                f, ld = np.array(hist).T
                bx.plot(f, ld / r["line_delay_true_s"], "-" + marker, color=colour, ms=3,
                        lw=0.8, alpha=0.8)
    ax.set_xlim(0, top), ax.set_ylim(0, top)
    ax.set_xlabel("true line delay (us/row)"), ax.set_ylabel("estimate after the bag (us/row)")
    ax.legend(fontsize=8), ax.grid(alpha=0.3)
    bx.axhspan(0.9, 1.1, color="0.9")
    bx.axhline(1.0, color="k", lw=0.8)
    bx.set_xlabel("frames seen"), bx.set_ylabel("estimate / true")
    bx.set_title("each estimate as it is revised", fontsize=9), bx.grid(alpha=0.3)
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def table(rows: list[dict]) -> str:
    lines = ["| case | group | true (us/row) | estimate (us/row) | error | status | "
             "calibrator | with the re-runs | rsvo_calibrate (refined) | ATE auto | ATE true | "
             "ATE auto / true | as the node / true | ATE two passes / true | ATE with 0 |",
             "|---" * 15 + "|"]
    for r in rows:
        e, true = r["estimate"], r["line_delay_true_s"]
        if e["line_delay_s"] is None:
            est, err = f"- ({e['reason']})", "-"
        else:
            est = f"{e['line_delay_s'] * 1e6:.1f} +- {e['std_s'] * 1e6:.1f}"
            err = (f"{100 * (e['line_delay_s'] - true) / true:+.0f} %" if true > 0
                   else f"{(e['line_delay_s'] - true) * 1e6:+.1f} us")
        rerun = r["estimate_rerun"]["line_delay_s"]
        if rerun is not None:
            rerun = (f"{rerun * 1e6:.1f} ({100 * (rerun - true) / true:+.0f} %)" if true > 0
                     else f"{rerun * 1e6:.1f}")
        refined = _with_error(r["estimate_refined"]["line_delay_s"], true)
        first = _with_error(r.get("estimate_calibrator", e)["line_delay_s"], true)
        lines.append(f"| {r['case']} | {r['group']} | {true * 1e6:.0f} | {est} | {err} | "
                     f"{e['status']} | {first or '-'} | {rerun or '-'} | {refined or '-'} | "
                     f"{r['ate_auto_m']:.3f} m | "
                     f"{r['ate_true_m']:.3f} m | "
                     f"{r['ate_auto_m'] / max(r['ate_true_m'], 1e-9):.2f} | "
                     f"{r['ate_auto_node_m'] / max(r['ate_true_m'], 1e-9):.2f} | "
                     f"{r['ate_two_pass_m'] / max(r['ate_true_m'], 1e-9):.2f} | "
                     f"{r['ate_zero_m']:.3f} m |")
    return "\n".join(lines)


def _with_error(value: float | None, true: float) -> str | None:
    if value is None:
        return None
    return (f"{value * 1e6:.1f} ({100 * (value - true) / true:+.0f} %)" if true > 0
            else f"{value * 1e6:.1f}")


def _row_line(k: int, n: int, row: dict) -> str:
    """The progress line of the k-th of n cases."""
    e = row["estimate"]
    got = "-" if e["line_delay_s"] is None else f"{e['line_delay_s'] * 1e6:.1f} us/row"
    return (f"[line_delay_table {k}/{n}] {row['case']}: true "
            f"{row['line_delay_true_s'] * 1e6:.0f} us/row, auto {got} ({e['status']}); ATE auto "
            f"{row['ate_auto_m']:.3f} m (two passes {row['ate_two_pass_m']:.3f} m), true "
            f"{row['ate_true_m']:.3f} m, zero {row['ate_zero_m']:.3f} m")


def main(argv: list[str] | None = None) -> int:
    p = argparse.ArgumentParser(prog="python -m rsvo_ros.tools.line_delay_table",
                                description=__doc__,
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("out", type=Path)
    p.add_argument("--frames", type=int, default=150)
    p.add_argument("--jobs", type=int, default=1, help="cases replayed side by side (1)")
    args = p.parse_args(argv)
    args.out.mkdir(parents=True, exist_ok=True)
    jobs = [(args.out, motion, sev, seed, ld, args.frames) for _, motion, sev, seed, ld in CASES]
    # in order, printed as each finishes; one job: in this process (rate_table.run_cases)
    rows = run_cases(run_case, jobs, max(args.jobs, 1), _row_line)
    for (group, *_), row in zip(CASES, rows, strict=True):
        row["group"] = group
    (args.out / "line_delay.json").write_text(json.dumps(rows, indent=1))
    text = table(rows) + "\n\n" + summary(rows) + "\n"
    (args.out / "line_delay.md").write_text(text)
    plot(args.out / "line_delay.png", rows)
    print(text)
    return 0


if __name__ == "__main__":
    sys.exit(main())
