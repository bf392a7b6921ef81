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


@pytest.mark.parametrize("args, message", [
    (["--window-option", "async_mapping=1"], "not a numeric WindowOptions field"),
    (["--window-option", "min_inlier_ratio=half"], "the value is not a number"),
    (["--window-option", "prior_p_step=-1"], "the value must be >= 0"),
    (["--resolution", "640"], "expected WIDTHxHEIGHT"),
])
def test_paced_run_rejects_bad_arguments(args, message, capsys):
    with pytest.raises(SystemExit):
        main(args)
    assert message in capsys.readouterr().err
