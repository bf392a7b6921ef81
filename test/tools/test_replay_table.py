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


def test_the_group_lines_report_the_scale_change_and_skip_runs_without_one():
    from rsvo_ros.tools.replay_table import format_table

    def cell(ate, rate):
        return {"ate_m": ate, "path_m": 10.0, "rpe_rot_deg": 0.1, "keyframe_w_rel_error": None,
                "scale_rate_percent_per_s": rate}

    cols = ["RS window", "GS window", "RS pairwise"]
    rows = [("vehicle", f"--seed {k}", {"RS window": cell(0.1, r), "GS window": cell(0.2, 1.0),
                                         "RS pairwise": cell(0.3, p)})
            for k, (r, p) in enumerate([(-2.0, 0.5), (-3.0, None), (1.0, -1.0)])]
    text = format_table("options", rows, cols)
    assert "scale change (median, % per s) RS window -2.0 (2 of 3 shrinking), RS pairwise -0.2" \
        in text, text
    rows = [(g, o, {c: dict(v, scale_rate_percent_per_s=None) for c, v in r.items()})
            for g, o, r in rows]
    assert "scale change" not in format_table("options", rows, cols)
