"""The odometry-twist table's formatting, figure and one short case (the full table is a
benchmark)."""

from __future__ import annotations

import math

import matplotlib.image as mpimg
import numpy as np

from rsvo_ros.tools.twist_table import main, plot, rates, run_case, summary, table


def _row(motion, severity, seed, rate, err, lin, inst, within, kf):
    return {"case": f"{motion}{seed}", "motion": motion, "severity": severity, "seed": seed,
            "frames": 90, "known": 84, "ate_m": 0.05, "keyframe_w_rel_error": kf,
            "angular_interval_deg_s_median": rate, "angular_error_vs_interval_deg_s_median": err,
            "linear_rel_error_vs_interval_median": lin, "angular_true_deg_s_median": rate,
            "angular_rel_error_median": inst, "angular_within_2_sigma": within}


def test_table_and_summary_give_each_bag_and_the_ranges_per_group():
    rows = [_row("vehicle", 1.0, 720, 40.0, 2.0, 0.03, 0.28, 1.0, 0.41),
            _row("vehicle", 1.0, 721, 40.0, 1.6, 0.02, 0.27, 0.95, 0.34),
            _row("walk", 2.0, 722, 70.0, 14.0, 1.1, 0.96, 1.0, None)]
    text = table(rows)
    assert "| vehicle sev. 1, seed 720 | 84 of 90 | 40.0 deg/s | 2.0 deg/s (5 %) | 3 % | 28 % | " \
           "100 % | 41 % |" in text
    assert "| walk sev. 2, seed 722 | 84 of 90 | 70.0 deg/s | 14.0 deg/s (20 %) | 110 % | 96 % " \
           "| 100 % | - |" in text
    s = summary(rows)
    assert "- vehicle sev. 1 (2 bags): angular 4-5 % of the interval's turn rate, linear 2-3 % " \
           "of its speed; against the instantaneous rate 27-28 %; within 2 sigma 95-100 %; " \
           "RS keyframe velocities 34-41 %" in s
    assert "- walk sev. 2 (1 bags):" in s and s.endswith("RS keyframe velocities -")


def test_one_short_case_and_its_figure(tmp_path):
    row = run_case(tmp_path, "vehicle", 0.5, 5, 16)
    assert row["frames"] == 16 and 0 < row["known"] < 16
    assert math.isfinite(row["angular_error_vs_interval_deg_s_median"])
    assert row["angular_error_vs_interval_deg_s_median"] < row["angular_interval_deg_s_median"]
    d = rates(tmp_path / "vehicle_sev0.5_seed5__out")
    assert len(d["stamp_s"]) == row["known"]
    assert d["published"].shape == d["true"].shape == d["interval"].shape == (row["known"], 3)
    # the published turn rate is nearer the interval's truth than no motion is
    assert np.median(np.linalg.norm(d["published"] - d["interval"], axis=1)) \
        < np.median(np.linalg.norm(d["interval"], axis=1))
    plot(tmp_path / "twist.png", {"vehicle": d, "empty": {k: v[:0] for k, v in d.items()}})
    assert mpimg.imread(tmp_path / "twist.png").shape[1] > 500
    assert main([str(tmp_path / "x"), "--jobs", "0"]) == 2
    assert main([str(tmp_path / "x"), "--frames", "5"]) == 2
