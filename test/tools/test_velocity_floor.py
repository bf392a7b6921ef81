"""python -m rsvo_ros.tools.velocity_floor: per-frame turn rates against perfect landmarks."""

from __future__ import annotations

import pytest

from rsvo_ros.tools.velocity_floor import main, velocity_floor


def test_a_frame_turn_rate_is_judged_against_what_it_can_represent(capsys):
    r = velocity_floor(1.0, noise_px=0.3, frames=range(5, 40, 5))
    # under 8-15 Hz shake the readout's mean rate is far from the instantaneous row-0 one ...
    assert r["readout_mean_vs_instantaneous"] > 0.5
    # ... and tracking against perfect landmarks lands much nearer the mean; the angular
    # acceleration during the readout models the shake better still
    assert r["w_error_constant"] < 0.5 * r["readout_mean_vs_instantaneous"]
    assert r["w_error_acceleration"] < r["w_error_constant"]
    assert r["row0_rotation_deg_acceleration"] < r["row0_rotation_deg_constant"]
    assert main(["--severity", "0.5", "--noise-px", "0"]) == 0
    assert "| 0.5 |" in capsys.readouterr().out
    with pytest.raises(SystemExit):
        main(["--noise-px", "-1"])
