"""The walk table: issue 13's walk targets on fresh hand-held walks."""

from __future__ import annotations

import json

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from rsvo_ros.tools.walk_table import (
    compare,
    format_comparison,
    main,
    parse_seeds,
    sim3_scale,
    size_by_second,
)


def test_seeds_and_ranges_are_parsed_and_bad_ones_refused():
    assert parse_seeds("1600-1602") == [1600, 1601, 1602]
    assert parse_seeds("3,5,9-10,5") == [3, 5, 9, 10]
    assert parse_seeds("7") == [7]
    for bad in ("x", "5-3", "-1", "1-", ""):
        with pytest.raises(ValueError, match="--seeds"):
            parse_seeds(bad)


def test_the_size_by_second_follows_an_estimate_that_shrinks():
    """A walk at 1 m/s whose estimate runs at 10 map units per metre for two seconds and at 5
    after (seen in another frame, turned and moved): the first two seconds at the start's size,
    the next two at half of it; a second standing still is left out."""
    t = np.arange(0, 5.0, 1 / 30)
    walked = np.minimum(t, 4.0)
    gt = np.column_stack([walked, 0.1 * np.sin(7 * walked), np.zeros_like(t)])
    step = np.diff(gt, axis=0, prepend=gt[:1])
    est = np.cumsum(np.where((t < 2.0)[:, None], 10.0, 5.0) * step, axis=0)
    est = est @ Rotation.from_rotvec([0.3, -0.2, 1.0]).as_matrix().T + [4.0, -2.0, 7.0]
    assert sim3_scale(gt[:60], est[:60]) == pytest.approx(10.0, rel=1e-6)
    sizes = dict(size_by_second(t, gt, est))
    assert sorted(sizes) == [0.0, 1.0, 2.0, 3.0]  # 4-5 s: the walker stood still
    assert sizes[0.0] == pytest.approx(1.0, abs=1e-6)
    assert sizes[1.0] == pytest.approx(1.0, abs=1e-6)
    assert sizes[2.0] == pytest.approx(0.5, abs=0.02)
    assert sizes[3.0] == pytest.approx(0.5, abs=1e-6)


def test_the_table_writes_and_replays_a_walk_and_refuses_bad_arguments(tmp_path, capsys):
    """One walk written and replayed; a broken bag beside it (its metadata unreadable) is
    reported in its row, the summary and stderr, the table is written with the other walk,
    and the tool exits 1; bad arguments exit 2."""
    out = tmp_path / "walks"
    broken = out / "bags" / "walk_sev0.7_120f_seed9"
    broken.mkdir(parents=True)
    (broken / "metadata.yaml").write_text("not: [a bag")
    assert main([str(out), "--seeds", "5,9", "--frames", "120"]) == 1
    rows = {r["seed"]: r for r in json.loads((out / "walks.json").read_text())["rows"]}
    r = rows[5]
    assert "error" not in r and r["frames"] == 120 and r["posed"] + r["held"] >= 118
    assert 0 < r["ate_share"] < 0.2 and 0.5 < r["scale_ratio"] < 2.0
    assert len(r["size_by_second"]) >= 2 and r["size_by_second"][0][1] == pytest.approx(1.0,
                                                                                        abs=0.2)
    assert "error" in rows[9] and rows[9]["ate_m"] is None
    assert (out / "walk_scale.png").stat().st_size > 0
    text = (out / "walks.md").read_text()
    assert "| 5 |" in text and "| 9 | not replayed:" in text
    assert "2 walks: under 3 % of the path on " in text and "not replayed: seeds [9]" in text
    captured = capsys.readouterr()
    assert "walks: under 3 % of the path" in captured.out
    assert "seed 9 not replayed" in captured.err
    # the same walk again, against the table above (read before it is overwritten): replayed
    # from its bag it is the same walk to the bit
    assert main([str(out), "--seeds", "5", "--frames", "120", "--against", str(out)]) == 0
    against = json.loads((out / "walks.json").read_text())["against"]
    assert against["seeds"] == 1 and against["same"] == 1 and against["ratios"] == {"5": 1.0}
    assert f"Against {out} (1 walks in both): ATE 1.000x" in capsys.readouterr().out
    assert "Against" in (out / "walks.md").read_text()
    assert (out / "walk_against.png").stat().st_size > 0
    (tmp_path / "other.json").write_text('{"rows": [{"frames": 3}]}')
    (tmp_path / "partial.json").write_text('{"rows": [{"seed": 5, "ate_m": 0.1}]}')
    (tmp_path / "text.json").write_text("seed 5: 0.1 m")
    for bad in (["--frames", "100"], ["--seeds", "a-b"], ["--decimation", "5"],
                ["--jobs", "0"], ["--stamp-jitter", "0.04"], ["--stamp-jitter", "-0.001"],
                ["--against", str(tmp_path / "none")],
                ["--against", str(tmp_path / "other.json")],
                ["--against", str(tmp_path / "partial.json")],
                ["--against", str(tmp_path / "text.json")]):
        assert main([str(tmp_path / "bad"), *bad]) == 2
        assert "walk_table:" in capsys.readouterr().err


def _row(seed, ate, share, scale):
    return {"seed": seed, "ate_m": ate, "ate_share": share, "scale_ratio": scale,
            "frames": 300, "posed": 300, "held": 0}


def test_a_table_is_compared_with_another_seed_by_seed():
    """Seeds in both tables only, a walk that failed in either left out; the ratios are
    this table's ATE over the other's, the counts each table's own over the shared seeds."""
    base = [_row(1, 0.10, 0.01, 1.00), _row(2, 0.20, 0.04, 1.20), _row(3, 0.10, 0.01, 1.0),
            _row(4, 0.30, 0.02, 1.0), {**_row(5, None, None, None), "error": "x"}]
    this = [_row(1, 0.10, 0.01, 1.00), _row(2, 0.10, 0.02, 1.05), _row(3, 0.40, 0.05, 1.5),
            _row(5, 0.10, 0.01, 1.0), _row(6, 0.10, 0.01, 1.0)]
    c = compare(this, base)
    assert c["seeds"] == 3 and c["ratios"] == {1: 1.0, 2: 0.5, 3: 4.0}
    assert c["ratio_gmean"] == pytest.approx(2.0 ** (1 / 3))
    assert c["same"] == 1 and c["within_10_percent"] == 1
    assert c["this"] == {"path": 2, "scale": 2} and c["base"] == {"path": 2, "scale": 2}
    text = format_comparison(c, "base")
    assert text.startswith("Against base (3 walks in both): ATE 1.260x in geometric mean "
                           "(per walk 0.50x, seed 2, to 4.00x, seed 3); 1 the same")
    assert "under 3 % of the path on 2 against 2" in text
    assert format_comparison(compare(this, []), "b") == "Against b: no seed replayed in both " \
                                                        "tables."
