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
    # index, frame ms, the tracker's and the window BA's part of it, outcome
    for _, frame_ms, track_ms, ba_ms, _ in out["slow_frames"]:
        assert 0 <= track_ms <= frame_ms + 0.2 and 0 <= ba_ms <= frame_ms + 0.2
    assert sum(f[2] > 0 for f in out["slow_frames"]) >= 39  # every frame after the first


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


def test_paced_run_steps_the_decimation_down_as_the_node_does(capsys):
    """--decimation auto with --drop: frames fed far faster than processed are dropped, so
    a whole span after the start-up (30 + 60 images) steps the tracking to half
    resolution, as the node's tracking_decimation_mode auto does (960 px wide: 480 at half,
    the least it takes); --motion renders another sequence."""
    assert main(["--frames", "200", "--rate", "300", "--resolution", "960x120", "--drop",
                 "--decimation", "auto", "--motion", "vehicle"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["motion"] == "vehicle" and out["decimation"] == "auto"
    assert len(out["decimation_steps"]) == 1 and out["decimation_steps"][0][1] == 2
    assert out["processed"] + out["dropped"] == 200
    # a run this short may not move enough for a Sim(3) fit: then it says so
    assert out["ate_m"] is not None or out["ate_error"]


def test_paced_run_samples_the_motion_at_the_rate_and_tracks_with_klt_alone(capsys):
    """--motion-at-rate renders the walk as a 15 Hz camera sees it (not the walk's 30 Hz
    frames fed at 15 Hz), --no-klt-shift-retry turns the tracker's re-tracking off (no frame
    re-tracked); the tracker's own time is reported and is part of each frame's."""
    runs = {}
    for flags in ([], ["--motion-at-rate", "--no-klt-shift-retry"]):
        assert main(["--frames", "20", "--rate", "15", "--mapping", "inline",
                     "--resolution", "320x240", *flags]) == 0
        runs[bool(flags)] = json.loads(capsys.readouterr().out)
    assert runs[False]["motion_rate_hz"] == 30.0 and runs[False]["klt_shift_retry"]
    assert runs[True]["motion_rate_hz"] == 15.0 and not runs[True]["klt_shift_retry"]
    assert runs[True]["frames_tracked_from_shift"] == 0
    for out in runs.values():
        assert 0 < out["track_ms_median"] <= out["track_ms_p95"]
        assert out["track_ms_median"] <= out["frame_ms_median"]
        assert 0 < out["track_s_total"] and sum(out["outcomes"].values()) == 20


@pytest.mark.parametrize("args, message", [
    (["--decimation", "0"], "--decimation must be 1-4 or auto"),
    (["--decimation", "auto"], "--decimation auto needs --drop"),
    (["--drop", "--mapping", "inline"], "--drop needs --mapping async"),
    (["--drop-every", "1"], "--drop-every must be 0 (none) or at least 2"),
    (["--window-option", "async_mapping=1"], "not a numeric WindowOptions field"),
    (["--window-option", "min_inlier_ratio=half"], "the value is not a number"),
    (["--window-option", "prior_p_step=-1"], "the value must be >= 0"),
    (["--resolution", "640"], "expected WIDTHxHEIGHT"),
    (["--resolution", "0x480"], "expected WIDTHxHEIGHT"),
])
def test_paced_run_rejects_bad_arguments(args, message, capsys):
    with pytest.raises(SystemExit):
        main(args)
    assert message in capsys.readouterr().err
