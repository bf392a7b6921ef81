"""The moving-people table's formatting, figure and one short case (the full table is a
benchmark)."""

from __future__ import annotations

import math

import matplotlib.image as mpimg

from rsvo_ros.tools.movers_table import main, plot, run_case, summary, table


def _row(motion, seed, movers, rs, gs):
    def r(ate):
        return {"ate_m": ate, "rpe_rot_deg": 0.2, "scale_drift": None, "posed": 90, "held": 1,
                "frames": 90, "inlier_ratio": 0.9}

    return {"case": f"{motion}{seed}_{movers}", "motion": motion, "severity": 1.0,
            "seed": seed, "group": "fresh", "movers": movers, "rs": r(rs), "gs": r(gs)}


def test_table_and_summary_compare_each_bag_with_itself_without_people():
    rows = [_row("walk", 823, 0, 0.02, 0.20), _row("walk", 823, 2, 0.08, 0.20),
            _row("walk", 824, 0, 0.05, 0.10), _row("walk", 824, 2, 0.05, 0.04)]
    text = table(rows)
    assert "| walk sev. 1, seed 823 (fresh) | 2 | 0.080 m | 0.200 m | 0.40 | 4.00 | 0.200 deg " \
           "| 0.90 | 90 (1) of 90 |" in text
    assert "| walk sev. 1, seed 823 (fresh) | 0 | 0.020 m | 0.200 m | 0.10 | 1.00 |" in text
    s = summary(rows).splitlines()
    assert s[0] == ("- fresh, walk, 0 people (2 bags): RS ATE 0.032 m in geometric mean; RS / "
                    "GS 0.22 (RS better on 2 of 2)")
    assert s[1] == ("- fresh, walk, 2 people (2 bags): RS ATE 0.063 m in geometric mean, 2.00x "
                    "the same bags without; RS / GS 0.71 (RS better on 1 of 2)")


def test_one_short_case_and_its_figure(tmp_path):
    row = run_case(tmp_path, "walk", 1.0, 5, "fresh", 1, 20)
    assert row["movers"] == 1 and row["case"].endswith("_movers1")
    for which in ("rs", "gs"):
        assert row[which]["frames"] == 20 and row[which]["posed"] >= 18
        assert math.isfinite(row[which]["ate_m"])
    plot(tmp_path / "movers.png", [row])
    assert mpimg.imread(tmp_path / "movers.png").shape[1] > 500
    assert main([str(tmp_path / "x"), "--jobs", "0"]) == 2
    assert main([str(tmp_path / "x"), "--frames", "5"]) == 2
