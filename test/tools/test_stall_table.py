"""The stalled-camera table's verdicts, formatting, argument checks and one short case (the
full table is a benchmark)."""

from __future__ import annotations

import pytest

from rsvo_ros.tools.stall_table import main, run_case, summary, table, verdict


def _row(group, motion, off, on, after=("held", "lost after 0.43 s without a frame: a new")):
    return {"group": group, "case": f"{motion}_x", "motion": motion, "gap_first": 40,
            "gap_frames": 12, "gap_s": 13 / 30, "ate_no_gap_m": 0.1, "ate_off_m": off,
            "ate_on_m": on, "after_off": ("posed", ""), "after_on": after}


def test_verdicts_table_and_summary():
    rows = [_row("looked at", "vehicle", 2.0, 0.5), _row("looked at", "vehicle", 1.0, 1.0),
            _row("looked at", "vehicle", 1.0, 2.0), _row("held out", "walk", 0.05, 0.05,
                                                         ("posed", ""))]
    assert [verdict(r) for r in rows] == ["better", "same", "worse", "same"]
    assert verdict(_row("g", "m", 1.0, None)) == "worse"  # never a pose
    assert verdict(_row("g", "m", None, 1.0)) == "same"
    text = table(rows)
    assert "| looked at | vehicle_x | 12 frames from 40 (0.43 s) | 0.100 | 2.000 | 0.500 | " \
           "held: lost after 0.43 s without a frame |" in text
    lines = summary(rows).splitlines()
    assert lines[0] == ("stall_table: looked at, vehicle: with the check better on 1, worse on "
                        "1, the same on 1 of 3 gaps; ATE with / without 0.79x in geometric mean")
    assert lines[1].startswith("stall_table: held out, walk: with the check better on 0, worse "
                               "on 0, the same on 1 of 1 gaps")


@pytest.mark.parametrize("args", [["--jobs", "0"], ["--cases", "0"], ["--frames", "100"]])
def test_bad_arguments_are_refused(args, capsys):
    assert main(args) == 2
    assert "stall_table: " in capsys.readouterr().err


def test_one_short_case():
    """A car with 12 frames left out (the window test's): the check's run starts a new map at
    the prediction, the run without it takes the aliased pose."""
    (row,) = run_case("looked at", "vehicle", 1.0, 200, 1e-4, ((40, 12),), 60)
    assert row["case"] == "vehicle_sev1_seed200_ld100us" and row["gap_s"] == pytest.approx(13 / 30)
    assert row["after_on"][0] == "held" and "without a frame" in row["after_on"][1]
    assert row["after_off"][0] == "posed"
    assert row["ate_on_m"] < 0.5 * row["ate_off_m"] and row["ate_no_gap_m"] < row["ate_on_m"]
    assert verdict(row) == "better"
