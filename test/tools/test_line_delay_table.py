"""The line-delay table's scoring and figure (the replays themselves are a benchmark)."""

from __future__ import annotations

import json

import matplotlib.image as mpimg
import numpy as np

from rsvo_ros.tools.line_delay_table import plot, summary, table, within


def _row(group, true, est, ate_auto=0.1, ate_true=0.1, history=(), ate_two_pass=None,
         refined=None, calibrator=None):
    return {"case": f"{group}{true}", "group": group, "line_delay_true_s": true,
            "estimate": {"line_delay_s": est, "std_s": None if est is None else 1e-6},
            "ate_auto_m": ate_auto, "ate_true_m": ate_true, "history": list(history),
            "ate_two_pass_m": ate_auto if ate_two_pass is None else ate_two_pass,
            # with the re-runs of the first frames, and as the node runs (no re-runs)
            "estimate_rerun": {"line_delay_s": est, "std_s": None if est is None else 1e-6},
            "ate_auto_node_m": 2 * ate_auto,
            # rsvo_calibrate's: refined in a second pass
            "estimate_refined": {"line_delay_s": est if refined is None else refined},
            # the calibrator's own estimate, before the pipeline refined it
            "estimate_calibrator": {"line_delay_s": est if calibrator is None else calibrator}}


def test_within_uses_the_relative_target_and_the_absolute_one_below_20_us():
    assert within(_row("fresh", 5e-5, 5.4e-5)) and not within(_row("fresh", 5e-5, 5.6e-5))
    assert within(_row("fresh", 1e-5, 1.19e-5)) and not within(_row("fresh", 1e-5, 1.21e-5))
    assert within(_row("fresh", 0.0, 1e-6)) and not within(_row("fresh", 0.0, 3e-6))
    assert not within(_row("fresh", 5e-5, None))  # no estimate: a miss


def test_summary_counts_per_group_and_the_figure_is_written(tmp_path):
    rows = [_row("held out", 5e-5, 5.2e-5, history=[[60, 7e-5], [100, 5.2e-5]]),
            _row("held out", 1e-4, 1.3e-4, ate_auto=0.2, ate_two_pass=0.105, refined=1.05e-4,
                 calibrator=0.98e-4),
            _row("held out", 0.0, 0.0), _row("fresh", 3e-5, None)]
    rows[1]["estimate_calibrator_last"] = {"line_delay_s": 1.02e-4}  # not in older rows
    text = summary(rows)
    assert "- held out: line delay within 10 % on 1 of 2 rolling-shutter bags (the " \
           "calibrator's where the refinement started: 2; its last estimate: 1; with the " \
           "re-runs: 1; rsvo_calibrate's, " \
           "refined in a second pass: 2; global shutter 1 of 1), " \
           "ATE auto within 10 % of ATE true on 1 of 2 (as the node, without the " \
           "re-runs: 0; two passes: 2); global shutter within 2 us/row on 1 of 1, its ATE auto " \
           "within 10 % on 1 (as the node: 0)" in text
    assert "- fresh: line delay within 10 % on 0 of 1" in text
    # rsvo_calibrate's refined estimate has a column of its own
    rows[1]["estimate"]["reason"] = rows[1]["estimate_rerun"]["reason"] = ""
    for r in rows:
        r["estimate"]["status"] = "estimated"
        r["ate_zero_m"] = 0.3
    rows[3]["estimate"]["reason"] = "collecting"
    md = table(rows)
    assert "| rsvo_calibrate (refined) |" in md.splitlines()[0]
    assert "| 98.0 (-2 %) | 130.0 (+30 %) | 105.0 (+5 %) |" in md.splitlines()[3]
    assert "| calibrator | with the re-runs |" in md.splitlines()[0]
    plot(tmp_path / "line_delay.png", rows)
    assert mpimg.imread(tmp_path / "line_delay.png").shape[1] > 500


def test_the_live_emulation_feeds_the_cases_as_the_node_runs(tmp_path, capsys):
    """python -m rsvo_ros.tools.live_line_delay: the table's rolling-shutter cases fed to an
    async-mapping pipeline at a camera's rate (newest frame first), one JSON row each and the
    counts; bad arguments refused."""
    from rsvo_ros.tools.live_line_delay import main as live_main
    from rsvo_ros.tools.live_line_delay import within as live_within

    out = tmp_path / "live.jsonl"
    assert live_main(["--cases", "1", "--frames", "24", "--rate", "60", "--refine-frames", "0",
                      "--json", str(out)]) == 0
    row = json.loads(out.read_text().splitlines()[0])
    assert row["case"] == "walk_sev1_seed0_ld20us" and row["frames"] == 24
    assert 1 <= row["processed"] <= 24 and row["refinement"] is None
    assert 3 <= row["posed"] <= row["processed"] and 0 < row["ate_m"] < 1.0  # a walk's metres
    assert "ate_true_m" not in row  # only with --with-true
    assert row["mapping_lag_s"] == 0.05  # the node's default
    assert row["status"] == "collecting" and row["final_s"] is None  # 24 frames: too few
    text = capsys.readouterr().out
    assert "the calibrator's estimate over all its windows within 10 % on 0 of 1 " \
        "rolling-shutter cases" in text
    assert "the estimate in use (the calibrator thread's last) within 10 % on 0 of 1" in text
    assert row["refinement_frames_unprocessed"] is None and row["running_s"] is None
    assert row["start_in_use_after_s"] is None  # no refinement
    assert "in use while the second pass ran on 0 of 1" in text
    assert live_within(5.4e-5, 5e-5) and not live_within(None, 5e-5)
    assert live_main(["--rate", "0"]) == 2
    assert live_main(["--cases", "0"]) == 2  # no case: refused, not a crash on no rows
    assert live_main(["--mapping-lag", "-0.1"]) == 2
    assert live_main(["--mapping-lag", "3"]) == 2
    assert live_main(["--cases", "1", "--frames", "12", "--rate", "60", "--refine-frames", "0",
                      "--mapping-lag", "0", "--with-true", "--json", str(out)]) == 0
    row = json.loads(out.read_text().splitlines()[0])
    assert row["mapping_lag_s"] == 0.0
    # the second run, the true line delay fixed: its own frames and ATE beside auto's
    assert 3 <= row["posed_true"] <= row["processed_true"] <= 12 and row["ate_true_m"] > 0
    assert "ATE with auto within 10 % of the true line delay's (both emulated live) on" \
        in capsys.readouterr().out


def test_the_live_emulation_keeps_the_path_as_the_node_does():
    """``keep_pose``: each posed frame by its stamp; frames processed again with the first
    line-delay estimate (``line_delay_rerun``) replace their published poses; a re-run frame
    that was never published (dropped) and a skipped frame stay out."""
    from rsvo_ros.odometry.pipeline import FrameResult
    from rsvo_ros.tools.live_line_delay import keep_pose

    def frame(stamp, x, revised=None):
        T = None if x is None else np.eye(4)
        if T is not None:
            T[0, 3] = x
        return FrameResult(0, stamp, "posed", "", T, np.eye(6), revised=revised)

    path = {}
    keep_pose(path, frame(1, 0.0))
    keep_pose(path, frame(3, 1.0))
    keep_pose(path, frame(4, None))  # skipped
    keep_pose(path, frame(5, 2.0, revised=[frame(1, 0.5), frame(2, 0.7), frame(3, 1.5)]))
    assert sorted(path) == [1, 3, 5]
    assert [path[s][0, 3] for s in (1, 3, 5)] == [0.5, 1.5, 2.0]


def test_the_live_emulation_counts_the_ate_near_the_true_line_delays():
    """ATE with auto against the true line delay's: within 10 % counted, the ratio's
    geometric mean over the rows with both, a row without an ATE a miss."""
    from rsvo_ros.tools.live_line_delay import ate_near_true

    rows = [{"ate_m": 0.105, "ate_true_m": 0.1}, {"ate_m": 0.2, "ate_true_m": 0.1},
            {"ate_m": 0.05, "ate_true_m": 0.1}, {"ate_m": None, "ate_true_m": 0.1}]
    line = ate_near_true(rows)
    assert "on 2 of 4 rolling-shutter cases" in line
    assert f"{(1.05 * 2.0 * 0.5) ** (1 / 3):.3f}x in geometric mean over 3" in line
    assert "on 0 of 1" in ate_near_true([{"ate_m": None, "ate_true_m": None}])
