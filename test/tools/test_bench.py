"""rsvo_bench: the paper's experiment runs end to end and reports what it promises."""

import json

import numpy as np

from rsvo_ros.tools.bench import PAPER_TABLE1, format_pair_times, main, pair_times


def test_quick_bench_writes_table_json_and_plot(tmp_path, capsys):
    out = tmp_path / "bench"
    assert main(["--trials", "3", "--levels", "1", "6", "--noise", "none", "gaussian",
                 "--output", str(out), "--no-progress"]) == 0
    table = capsys.readouterr().out
    for text in ("noise-free", "gaussian noise", "paper MRSVO", "RS (ours)", "MVO (ours)",
                 "GS OpenCV USAC_MAGSAC", "Time per pair"):
        assert text in table
    data = json.loads((out / "bench.json").read_text())
    assert data["meta"]["trials_per_cell"] == 3 and data["meta"]["focal_px"] == 1000.0
    assert len(data["records"]) == 2 * 2 * 3 * 3  # levels x noises x trials x methods
    s = data["summary"]["none"]
    # noise-free level 6: the RS model explains the RS correspondences, GS cannot
    assert s["RS (ours)"]["6"]["rot_err_deg"]["median"] < 0.05
    assert s["RS (ours)"]["6"]["inlier_ratio"]["median"] > 0.97
    assert s["GS OpenCV USAC_MAGSAC"]["6"]["rot_err_deg"]["median"] > 0.5
    assert s["RS (ours)"]["1"]["rot_err_deg"]["mean"] < 0.01  # no distortion: exact
    assert (out / "bench_boxplot.png").stat().st_size > 20_000
    assert np.isclose(PAPER_TABLE1["none"]["MRSVO"]["rot"][5], 0.475)
    # the README's table: a header, a separator, per noise 4 + 4 + 2 + 2 rows, levels 1 and 6
    md = (out / "bench.md").read_text().splitlines()
    assert md[0] == "| noise | metric | method | L1 | L6 |" and len(md) == 2 + 2 * 12 + 2
    assert md[2].startswith("| none | rotation (deg) | MVO (ours) |")
    mean_l6 = s["RS (ours)"]["6"]["rot_err_deg"]["mean"]
    assert md[4].startswith("|  |  | **RS (ours)** |")  # noise-free RS rotation means
    assert md[4].rstrip(" |").endswith(f"{mean_l6:.3f}")
    assert md[14].startswith("| Gaussian 1 px | rotation (deg) | MVO (ours) |")
    # issue 14's figure: each method's median per pair over all 12 of its pairs, in the
    # output, the JSON and under the table
    times = data["pair_times"]
    for method in ("RS (ours)", "GS OpenCV USAC_MAGSAC", "MVO (ours)"):
        mine = [r["time_ms"] for r in data["records"] if r["method"] == method]
        assert len(mine) == 12 == times["pairs"][method]
        assert times["median_ms"][method] == np.median(mine)
    ratio = times["median_ms"]["RS (ours)"] / times["median_ms"]["GS OpenCV USAC_MAGSAC"]
    assert np.isclose(times["rs_over_magsac"], ratio)
    line = md[-1]
    assert md[-2] == "" and line in table.splitlines()
    assert line.startswith("Time per pair over all 12 pairs, median: ")
    assert f"RS (ours) {times['median_ms']['RS (ours)']:.2f} ms" in line
    assert f"(RS / MAGSAC {ratio:.2f} in this run)" in line


def test_the_pair_times_line_says_whether_the_target_is_met():
    fast = {"median_ms": {"RS (ours)": 11.0, "GS OpenCV USAC_MAGSAC": 7.0}, "target_ms": 12.0,
            "pairs": {"RS (ours)": 5, "GS OpenCV USAC_MAGSAC": 5}, "rs_over_magsac": 11 / 7}
    assert format_pair_times(fast).endswith(
        "(RS / MAGSAC 1.57 in this run); the RS target of 12 ms per pair: met")
    slow = dict(fast, median_ms={"RS (ours)": 12.5, "GS OpenCV USAC_MAGSAC": 7.0})
    assert format_pair_times(slow).endswith("12 ms per pair: not met")
    # a run without MAGSAC (or with no RS pair) has no ratio and says nothing of it
    no_gs = pair_times([])
    assert no_gs["rs_over_magsac"] is None and no_gs["median_ms"] == {}
    assert "MAGSAC" not in format_pair_times(no_gs) and "target" not in format_pair_times(no_gs)


def test_bad_trials_exit_2(tmp_path):
    assert main(["--trials", "0", "--output", str(tmp_path), "--no-progress"]) == 2
