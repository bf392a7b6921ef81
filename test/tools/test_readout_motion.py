"""python -m rsvo_ros.tools.readout_motion: what each motion model leaves of the turning during
one readout."""

from __future__ import annotations

import numpy as np

from rsvo_ros.tools.readout_motion import main, parse_case, unexplained_px


def test_each_richer_model_explains_more_of_a_shaking_walks_readout():
    res = unexplained_px(parse_case("walk:2:0:default", 12))
    gs, cv, ca = (np.median(res[k]) for k in ("gs", "cv", "ca"))
    assert gs > 1.5 * cv and cv > 5.0 * ca > 0  # constant velocity leaves pixels: shake


def test_readout_motion_prints_a_table_and_rejects_bad_cases(capsys):
    assert main(["--frames", "8", "--cases", "vehicle:1:0:5e-5"]) == 0
    assert "| vehicle:1:0:5e-5 | 18.0 |" in capsys.readouterr().out
    assert main(["--frames", "8", "--cases", "walk:1"]) == 2
    assert "motion:severity:seed:line_delay" in capsys.readouterr().err
    assert main(["--frames", "8", "--cases", "paper:1:0:default"]) == 2
