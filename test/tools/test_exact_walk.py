"""The exact-track walk: the window backend fed the renderer's exact RS projections."""

import json

import pytest

from rsvo_ros.tools import exact_walk as ew

SEGMENT = dict(seed=2106, rate=15.0, start=166, stop=200)  # a walk past a wall (README)


def test_a_global_shutter_walk_keeps_its_scale_and_fits_to_the_noise():
    out = ew.exact_walk(**SEGMENT, line_delay=0.0, noise_px=0.0)
    assert out["first_tracked"] is not None and out["first_tracked"] < 180
    assert out["outcomes"].get("posed: tracked", 0) >= 20
    assert abs(out["scale_change"] - 1.0) < 0.05
    assert out["residual_px_median"] < 0.05  # the model is exact without rolling shutter


def test_a_shaken_readout_leaves_a_misfit_that_its_quadratic_fit_removes():
    exact = ew.exact_walk(**SEGMENT, noise_px=0.0)
    fitted = ew.exact_walk(**SEGMENT, noise_px=0.0, readout_fit="quadratic")
    # the 8-15 Hz shake turns the camera by a cubic in the row time that the model's turn rate
    # and angular acceleration cannot follow; fitted to a quadratic, about half of it is gone
    # (the rest: the translation's acceleration in the readout and the priors)
    assert exact["residual_px_median"] > 0.15
    assert fitted["residual_px_median"] < 0.7 * exact["residual_px_median"]  # 0.54x measured


def test_the_command_line_refuses_a_too_short_segment(capsys):
    with pytest.raises(SystemExit):
        ew.main(["--start", "10", "--stop", "20"])
    assert "at least" in capsys.readouterr().err


def test_the_command_line_prints_one_json_line(capsys):
    assert ew.main(["--start", "166", "--stop", "190", "--resolution", "640x360",
                    "--line-delay", "0", "--points", "200"]) == 0
    out = json.loads(capsys.readouterr().out)
    assert out["frames"] == [166, 190] and out["readout_fit"] == "exact"
