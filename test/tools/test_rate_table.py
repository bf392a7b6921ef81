"""The frame-rate table's formatting, figure and one short case (the full table is a
benchmark)."""

from __future__ import annotations

import math

import matplotlib.image as mpimg

from rsvo_ros.tools.rate_table import main, plot, run_case, summary, table


def _row(motion, seed, rate, rs, gs, est, auto, posed=40):
    def r(ate, rpe):
        return {"ate_m": ate, "rpe_rot_deg": rpe, "posed": posed, "held": 0, "frames": 40}

    return {"case": f"{motion}{seed}_{rate}", "motion": motion, "severity": 1.0, "seed": seed,
            "rate_hz": rate, "frames": 40, "rs": r(rs, 0.2), "gs": r(gs, 0.8),
            "auto": {**r(auto, 0.2), "status": "estimated", "line_delay_s": est}}


def test_table_and_summary_give_each_bag_and_the_counts_per_rate():
    rows = [_row("walk", 810, 10.0, 0.05, 0.10, 4.2e-5, 0.052),
            _row("vehicle", 810, 10.0, 0.02, 0.01, 6.0e-5, 0.030),
            _row("walk", 810, 60.0, 0.02, 0.08, None, None, posed=39)]
    text = table(rows)
    assert "| walk sev. 1, seed 810 | 10 Hz | 40 (0) of 40 | 0.050 m | 0.100 m | 0.50 | " \
           "0.200 / 0.800 deg | 42.0 us/row (+5 %) | 1.04 |" in text
    assert "| walk sev. 1, seed 810 | 60 Hz | 39 (0) of 40 | 0.020 m | 0.080 m | 0.25 | " \
           "0.200 / 0.800 deg | - | - |" in text
    s = summary(rows).splitlines()
    assert s[0] == ("- 10 Hz (2 bags): RS / GS ATE 1.00 in geometric mean (0.50-2.00; RS better "
                    "on 1), frames posed 80 of 80, RS rotation error per frame 0.200 deg (GS "
                    "0.800); line delay auto within 10 % on 1, its ATE within 10 % of the true "
                    "line delay's on 1")
    assert s[1].startswith("- 60 Hz (1 bags): RS / GS ATE 0.25") and "posed 39 of 40" in s[1]


def test_one_short_case_and_its_figure(tmp_path):
    row = run_case(tmp_path, "vehicle", 0.5, 5, 15.0, 1.2)
    assert row["frames"] == 18 and row["rate_hz"] == 15.0
    for which in ("rs", "gs", "auto"):
        assert row[which]["frames"] == 18 and row[which]["posed"] >= 16
        assert math.isfinite(row[which]["ate_m"])
    assert row["auto"]["status"] in ("collecting", "estimated", "converged", "not observable")
    plot(tmp_path / "rate.png", [row])
    assert mpimg.imread(tmp_path / "rate.png").shape[1] > 500
    assert main([str(tmp_path / "x"), "--jobs", "0"]) == 2
    assert main([str(tmp_path / "x"), "--seconds", "0.5"]) == 2
