"""The replay table's keyframe velocity figures against the synthetic trajectory."""

from __future__ import annotations

import numpy as np

from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig
from rsvo_ros.tools.replay_table import readout_w_errors


def test_keyframe_turn_rates_are_judged_against_the_mean_over_the_readout():
    config = dict(motion="walk", severity=1.0, seed=3, frames=40)
    r = SequenceRenderer(SynthConfig(**config))
    stamps = [round(k / r.config.rate_hz * 1e9) for k in range(0, 40, 4)]

    def keyframes(w_of):
        return {"velocities": [{"stamp_ns": s, "w": list(w_of(k)), "v": [0.0, 0.0, 0.0]}
                               for k, s in zip(range(0, 40, 4), stamps, strict=True)]}

    exact = readout_w_errors(r, keyframes(r.readout_turn_rate))
    assert exact["keyframe_w_readout_error"] < 1e-9
    assert exact["readout_w_vs_instantaneous"] > 0.3  # hand-held shake within the readout
    # the instantaneous row-0 rate (what the bag's ground truth carries) is that far off
    inst = readout_w_errors(r, keyframes(lambda k: r.frame_pose(k)[3]))
    assert inst["keyframe_w_readout_error"] > 0.3
    half = readout_w_errors(r, keyframes(lambda k: 0.5 * r.readout_turn_rate(k)))
    assert np.isclose(half["keyframe_w_readout_error"], 0.5)
    assert readout_w_errors(r, {}) == {}  # the pairwise backend: no keyframes
