"""The auto-exposure table's scoring, figure and one short case (the full table is a
benchmark)."""

from __future__ import annotations

import math

import matplotlib.image as mpimg

from rsvo_ros.tools.brightness_table import main, plot, run_case, summary, table


def _row(group, gain, on, off, gs, flat=None, seed=1):
    return {"case": f"walk{seed}", "group": group, "motion": "walk", "severity": 1.0,
            "seed": seed, "gain_variation": gain, "frames_compensated": 5, "frames": 9,
            "ate_rs_m": on, "ate_rs_uncompensated_m": off, "ate_gs_m": gs,
            "ate_rs_constant_m": flat}


def test_summary_gives_geometric_means_per_group_and_the_figure_is_written(tmp_path):
    rows = [_row("held out", 0.3, 0.1, 0.4, 1.0, 0.1), _row("held out", 0.3, 0.2, 0.2, 0.1, 0.4),
            _row("looked at", 0.2, 0.1, 0.1, 1.0)]
    text = summary(rows)
    # (0.25 * 1) ** 0.5 = 0.5, better on one; RS / GS (0.1 * 2) ** 0.5
    assert "- held out, gain variation 0.3 (2 bags): RS compensated / not 0.50 (better on 1), " \
           "RS / GS 0.45 (RS better on 1; not compensated 0.89); against the same bags at " \
           "constant brightness: compensated 0.71, not 1.41" in text
    assert "- looked at, gain variation 0.2 (1 bags): RS compensated / not 1.00 (better on 0)" \
           in text and text.count("constant brightness") == 1
    assert "| walk sev. 1, seed 1 | held out | 0.3 | 5 of 9 | 0.100 | 0.100 | 0.400 | 1.000 |" \
           in table(rows)
    plot(tmp_path / "brightness.png", rows)
    assert mpimg.imread(tmp_path / "brightness.png").shape[1] > 500


def test_one_short_case_replays_every_variant(tmp_path):
    row = run_case(tmp_path, "held out", "walk", 1.0, 3, 0.3, True, 6)
    assert row["frames"] == 6 and 0 < row["frames_compensated"] <= 5
    for key in ("ate_rs_m", "ate_rs_uncompensated_m", "ate_gs_m", "ate_rs_constant_m"):
        assert math.isfinite(row[key]) and row[key] >= 0.0
    assert main([str(tmp_path / "x"), "--jobs", "0"]) == 2
