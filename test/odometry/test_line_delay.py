"""line_delay auto: the line delay from the video (window BA problems re-solved per candidate
readout with the velocities held to the trajectory)."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
from conftest import ground_truth_pose

from rsvo_ros.odometry.line_delay import (
    LineDelayCalibrator,
    LineDelayEstimate,
    LineDelayOptions,
    _parabola_min,
)
from rsvo_ros.odometry.pipeline import OdometryPipeline, PipelineOptions
from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig
from rsvo_ros.tools.replay import accuracy

FRAMES = 150


def _run(line_delay_true: float, auto: bool, seed: int = 0):
    cfg = SynthConfig(frames=FRAMES, motion="walk", severity=1.0, seed=seed,
                      line_delay=line_delay_true)
    renderer = SequenceRenderer(cfg)
    pipe = OdometryPipeline(renderer.K, None, 0.0 if auto else line_delay_true,
                            PipelineOptions(line_delay_auto=auto))
    est, gt = {}, {}
    for f in renderer:
        s = round(f.stamp * 1e9)
        est[s] = pipe.process(s, f.image).T_world_cam
        gt[s] = ground_truth_pose(f)
    pipe.close()
    return pipe, accuracy(gt, est)["ate_m"]["rmse"]


@pytest.fixture(scope="module")
def auto_50():
    return _run(5e-5, auto=True)


def test_parabola_minimum():
    x = np.arange(0, 1.01, 0.1)
    assert _parabola_min(x, (x - 0.43) ** 2) == pytest.approx(0.43)
    assert _parabola_min(x, x) == 0.0  # at zero: a global shutter
    assert _parabola_min(x, -x) is None  # at the top edge: not trusted


def test_auto_finds_the_line_delay_of_a_shaken_walk_and_keeps_its_accuracy(auto_50):
    """50 us/row (a 18 ms readout of a 33 ms frame interval): the estimate is within 25 % (it
    comes out high under shake, see the README) and the ATE within 10 % of the true value's."""
    pipe, ate_auto = auto_50
    e = pipe.line_delay_estimate
    assert e.status in ("estimated", "converged"), e
    assert abs(e.line_delay_s - 5e-5) < 0.25 * 5e-5, e
    assert pipe.line_delay == e.line_delay_s  # and it is used
    assert 0 < e.std_s < 0.2 * e.line_delay_s and e.readout_s == pytest.approx(
        e.line_delay_s * 360)
    assert pipe.line_delay_history and pipe.line_delay_history[-1]["line_delay_s"] \
        == e.line_delay_s
    _, ate_true = _run(5e-5, auto=False)
    assert ate_auto <= 1.10 * ate_true, (ate_auto, ate_true)


def test_auto_on_a_global_shutter_comes_out_at_zero():
    pipe, _ = _run(0.0, auto=True)
    e = pipe.line_delay_estimate
    assert e.status == "converged" and e.line_delay_s < 2e-6, e
    assert pipe.line_delay == e.line_delay_s


def test_without_rotation_it_says_so(auto_50):
    pipe, _ = auto_50
    cal = pipe.calibrator
    still = LineDelayCalibrator(cal.height, LineDelayOptions())
    for win in cal.windows:  # the same windows, as if the camera had not rotated
        mu = win.problem.prior_mu.copy()
        mu[:, :3] = 0.0
        prob = dataclasses.replace(win.problem, prior_mu=mu)
        still.add_window(prob, 0.0)
        still.windows[-1].obs_rows, still.windows[-1].lm_rows = win.obs_rows, win.lm_rows
    still.frames = cal.frames
    e = still.estimate(1 / 30)
    assert e.status == "not observable" and "rotation" in e.reason and e.line_delay_s is None
    few = LineDelayCalibrator(360)
    assert few.estimate(1 / 30).status == "collecting"


def test_not_observable_at_first_goes_back_to_the_given_value():
    K = np.array([[500.0, 0, 320], [0, 500.0, 180], [0, 0, 1]])
    pipe = OdometryPipeline(K, None, 0.0, PipelineOptions(line_delay_auto=True))
    assert pipe.line_delay > 0  # the nominal half-frame readout while it collects
    pipe._take_estimate(LineDelayEstimate("not observable", reason="too little rotation"), 1)
    assert pipe.line_delay == 0.0 and pipe.window.line_delay == 0.0
    assert pipe.line_delay_history[-1]["status"] == "not observable"
    pipe.close()
