"""python -m rsvo_ros.tools.paced_run: the README's in-process long-run A/B harness."""

from __future__ import annotations

import json

import pytest

from rsvo_ros.tools.paced_run import main


def test_paced_run_reports_ate_times_and_outcomes(capsys):
    assert main(["--frames", "40", "--rate", "30", "--resolution", "320x240",
                 "--window-option", "min_inlier_ratio=0.4", "--slow-ms", "0"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["mapping"] == "async" and out["window_options"] == {"min_inlier_ratio": 0.4}
    assert sum(out["outcomes"].values()) == 40 and 0 < out["ate_m"] < 1.0
    assert 0 < out["frame_ms_median"] <= out["frame_ms_p95"]
    assert len(out["slow_frames"]) == 40  # every frame is slower than 0 ms


def test_paced_run_drop_applies_the_nodes_newest_frame_policy(capsys):
    # at 1000 frames/s nearly every frame arrives while another is processed: most are
    # replaced by newer ones and dropped, and every frame is counted one way or the other
    assert main(["--frames", "40", "--rate", "1000", "--resolution", "320x240", "--drop"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["processed"] + out["dropped"] == 40 and out["dropped"] > 10
    assert sum(out["outcomes"].values()) == out["processed"]
    assert 0 < out["delay_ms_median"] <= out["delay_ms_p95"]


def test_paced_run_drop_every_leaves_out_every_nth_frame(capsys):
    assert main(["--frames", "30", "--mapping", "inline", "--resolution", "320x240",
                 "--drop-every", "3", "--no-flow-prediction"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["dropped"] == 10 and out["processed"] == 20 and not out["flow_prediction"]
    assert sum(out["outcomes"].values()) == 20 and "delay_ms_median" not in out


@pytest.mark.parametrize("args, message", [
    (["--drop", "--mapping", "inline"], "--drop needs --mapping async"),
    (["--drop-every", "1"], "--drop-every must be 0 (none) or at least 2"),
    (["--window-option", "async_mapping=1"], "not a numeric WindowOptions field"),
    (["--window-option", "min_inlier_ratio=half"], "the value is not a number"),
    (["--window-option", "prior_p_step=-1"], "the value must be >= 0"),
    (["--resolution", "640"], "expected WIDTHxHEIGHT"),
])
def test_paced_run_rejects_bad_arguments(args, message, capsys):
    with pytest.raises(SystemExit):
        main(args)
    assert message in capsys.readouterr().err
