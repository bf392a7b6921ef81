"""The latency probe's bookkeeping (the probe itself runs against a live node: README)."""

from __future__ import annotations

import numpy as np
import pytest

from rsvo_ros.core.geometry import so3_exp
from rsvo_ros.ros.dds import LARGE_IMAGES_PROFILE, PROFILE_ENV
from rsvo_ros.ros.latency import (
    _frame_counts,
    dds_profile_name,
    live_ate,
    summary_table,
    tail_frames,
)


def test_frame_counts_come_from_the_nodes_diagnostics():
    diag = {"received": "90", "processed": "85", "dropped": "5", "held": "0",
            "tracking_state": "tracking", "line_delay": "5e-05"}
    assert _frame_counts(diag) == {"received": 90, "processed": 85, "dropped": 5, "held": 0}
    assert _frame_counts({}) == {}  # no diagnostics yet


def _row(resolution, rate, odometry, p95, cpu=50.0, profile="default", decimation=None):
    extra = {} if decimation is None else {"tracking_decimation": decimation}
    return {"rate_hz": rate, "resolution": resolution, "sent": 300, "odometry": odometry,
            **extra, "dds_profile": profile, "image_delay_ms_median": "12.5",
            "latency_ms_median": 20.0, "latency_ms_p95": p95, "node_cpu_percent": cpu,
            "tracking_ms_median": "12.0", "mapping_ms_median": "40.0",
            "publishing_ms_median": "1.0",
            "node_frames": {"received": 300, "processed": odometry, "dropped": 300 - odometry,
                            "held": 0}}  # fmt: skip


def test_summary_table_sorts_rows_and_judges_each_target():
    table = summary_table([_row("1280x720", 30.0, 285, 70.0), _row("640x480", 10.0, 300, 25.0),
                           _row("1280x720", 15.0, 290, 61.0, cpu=160.0)])
    lines = table.splitlines()
    assert len(lines) == 2 + 3
    assert lines[2].startswith("| 640x480 | 10 Hz | default | 1 | 300 / 300 (100.0 %) | "
                               "20 / 25 ms | 12.5 ms |")
    assert lines[2].endswith("| - |")  # no target at 640x480 10 Hz
    # 285 of 300 is 95 %: >= 90 % met, p95 70 <= 80 met
    assert ">= 90 % met; p95 <= 80 ms met" in lines[4]
    # 290 of 300 is 96.7 % (< 98 %), p95 61 > 60, 1.6 cores > 1.5
    assert ">= 98 % not met; p95 <= 60 ms not met; CPU <= 1.5 cores not met" in lines[3]


def test_rows_of_both_dds_profiles_sit_side_by_side():
    table = summary_table([_row("1280x720", 15.0, 300, 45.0, profile="large_images"),
                           _row("640x480", 30.0, 300, 40.0), _row("1280x720", 15.0, 299, 70.0)])
    lines = table.splitlines()[2:]
    assert [line.split(" | ")[2] for line in lines] == ["default", "default", "large_images"]
    assert "p95 <= 60 ms not met" in lines[1] and "p95 <= 60 ms met" in lines[2]


def test_rows_of_each_tracking_decimation_sit_side_by_side():
    """Runs of the node at full resolution (rows without the field: before it existed), at
    tracking_decimation 2 and in auto mode (after the fixed ones, saying where it ended), each
    judged against the same target."""
    auto = _row("1280x720", 30.0, 275, 70.0, decimation=2)
    auto["tracking_decimation_mode"] = "auto"
    table = summary_table([auto, _row("1280x720", 30.0, 291, 56.0, decimation=2),
                           _row("1280x720", 30.0, 220, 130.0)])
    lines = table.splitlines()[2:]
    assert [line.split(" | ")[3] for line in lines] == ["1", "2", "auto (ended at 2)"]
    assert ">= 90 % not met; p95 <= 80 ms not met" in lines[0]
    assert ">= 90 % met; p95 <= 80 ms met" in lines[1]
    assert "275 / 300" in lines[2]


def test_the_probe_names_the_dds_profile_it_runs_with(monkeypatch, tmp_path):
    monkeypatch.delenv(PROFILE_ENV, raising=False)
    assert dds_profile_name() == "default"
    monkeypatch.setenv(PROFILE_ENV, str(LARGE_IMAGES_PROFILE))
    assert dds_profile_name() == "large_images"
    other = tmp_path / "mine.xml"
    other.write_text("<profiles/>")
    monkeypatch.setenv(PROFILE_ENV, str(other))
    assert dds_profile_name() == str(other)


def test_the_tail_frames_are_the_slowest_twentieth_in_frame_order():
    """A run of 100 frames with odometry whose frames 40-44 took 90-94 ms (the rest 20 ms,
    frame 7 missing): the tail is those five, by frame index; a short run keeps one frame."""
    delays = {k: 20.0 + k * 1e-3 for k in range(101) if k != 7}
    delays.update({40 + i: 94.0 - i for i in range(5)})
    assert tail_frames(delays) == [[40, 94.0], [41, 93.0], [42, 92.0], [43, 91.0], [44, 90.0]]
    assert tail_frames({3: 10.0, 5: 30.04}) == [[5, 30.0]]
    assert tail_frames({}) == []


def test_the_live_ate_aligns_the_odometry_to_the_truth_by_sim3():
    """The odometry received is judged as the replay's trajectory is: ATE of the positions
    after a Sim(3) alignment, on the stamps it shares with the frames sent; too few poses are
    said."""
    truth = {1000 + 33 * k: np.array([0.05 * k, 0.01 * np.sin(k), 0.0]) for k in range(40)}
    # the same trajectory in another world frame and scale, one frame missing, one pose of a
    # frame never sent
    R, t = so3_exp(np.array([0.1, -0.3, 0.2])), np.array([1.0, 2.0, 3.0])
    odom = {s: 2.5 * (R @ p + t) for s, p in truth.items()}
    del odom[1000 + 33 * 7]
    odom[5] = np.zeros(3)
    assert live_ate(truth, odom)["ate_m"] == pytest.approx(0.0, abs=1e-9)
    off = dict(odom)
    off[1000 + 33 * 20] = off[1000 + 33 * 20] + [2.5, 0.0, 0.0]  # 1 m off, in the truth's units
    assert 0.05 < live_ate(truth, off)["ate_m"] < 0.3
    few = live_ate(truth, {1000: np.zeros(3)})
    assert few["ate_m"] is None and "1 poses with ground truth" in few["ate_error"]


def test_the_table_says_how_the_motion_was_sampled_and_the_live_ate():
    old = _row("1280x720", 15.0, 300, 50.0)  # a row from before the fields: 30 Hz motion
    new = _row("1280x720", 15.0, 300, 55.0, profile="large_images")
    new.update(motion_rate_hz=15.0, ate_m=0.1234)
    lines = summary_table([old, new]).splitlines()
    assert "| motion per frame | ATE | target |" in lines[0]
    assert "| 30 Hz | - | >= 98 % met" in lines[2]
    assert "| 15 Hz | 0.123 m | >= 98 % met" in lines[3]


def test_rows_of_each_walk_seed_sit_side_by_side_and_say_their_seed():
    """RSVO_LATENCY_SEEDS runs each row on several walks: the rows sort by seed within a
    setting, and a seed other than the default 0 is named beside the motion (rows from before
    the field are seed 0)."""
    rows = []
    for seed in (7, 0, None):
        r = _row("1280x720", 30.0, 290, 60.0)
        r.update(motion_rate_hz=30.0, ate_m=0.1)
        if seed is not None:
            r["seed"] = seed
        rows.append(r)
    lines = summary_table(rows).splitlines()[2:]
    assert [line.count("(seed 7)") for line in lines] == [0, 0, 1]
    assert all("| 30 Hz | 0.100 m |" in line for line in lines[:2])
    assert "| 30 Hz (seed 7) | 0.100 m |" in lines[2]


@pytest.mark.parametrize("rate, at_rate, readout_s", [
    (30.0, True, 1.0 / 30.0),  # the readout capped at the frame interval
    (15.0, True, 0.036),
    (30.0, False, 0.036),  # the walk's own frames (30 Hz) without a frame rate: 36 ms
])
def test_the_probe_prints_the_line_delay_it_renders_with(rate, at_rate, readout_s, capsys):
    """The node must be told the line delay of the frames it gets: with the motion sampled at
    30 Hz they are read out in one frame interval (33 ms), not the 36 ms the latency table
    gave every row's node until the forty-seventh session. ``--print-line-delay`` prints the
    renderer's, as the probe's ``--bag`` records it, without starting ROS."""
    from rsvo_ros.ros.latency import line_delay_text, main
    from rsvo_ros.sim.synth import SynthConfig

    argv = ["--rate", str(rate), "--resolution", "640x480", "--motion", "walk",
            "--print-line-delay"] + (["--motion-at-rate"] if at_rate else [])
    assert main(argv) == 0
    text = capsys.readouterr().out.strip()
    assert float(text) == pytest.approx(readout_s / 480, rel=1e-10)
    cfg = SynthConfig(frames=2, motion="walk", width=640, height=480,
                      frame_rate=rate if at_rate else None)
    assert text == line_delay_text(cfg.tau)


def test_the_line_delay_print_takes_one_rate(capsys):
    from rsvo_ros.ros.latency import main

    with pytest.raises(SystemExit) as exc:
        main(["--rate", "15", "30", "--print-line-delay"])
    assert exc.value.code == 2
    assert "--print-line-delay takes one --rate, got 2" in capsys.readouterr().err


def test_the_nodes_line_delay_is_checked_against_the_rendered_one():
    from rsvo_ros.ros.latency import line_delay_matches, line_delay_text

    tau = 1.0 / 30.0 / 480
    assert line_delay_matches(line_delay_text(tau), tau)  # the printed text: the same
    assert line_delay_matches(repr(tau), tau)
    assert not line_delay_matches("7.5e-05", tau)  # the 36 ms readout at 30 Hz
    assert not line_delay_matches("0.0", tau) and line_delay_matches("0.0", 0.0)
    assert not line_delay_matches("auto", tau)
    assert line_delay_matches(None, tau)  # no diagnostics yet: nothing to say


def test_the_probe_rejects_a_negative_seed_before_it_starts(capsys):
    from rsvo_ros.ros.latency import main

    with pytest.raises(SystemExit):
        main(["--seed", "-1"])
    assert "--seed must be a non-negative integer, got -1" in capsys.readouterr().err


def test_the_probe_stops_with_a_clear_message_when_no_node_listens(tmp_path):
    """Frames sent before the node subscribes would be counted as frames it missed (a node
    compiling its solver on its first start took 57 s, past the old fixed 30 s wait): without
    a node the probe gives up after --wait with exit 2, names what to do, and writes no
    result."""
    import subprocess
    import sys

    from conftest import ros_domain, ros_test_env

    out = tmp_path / "latency.json"
    proc = subprocess.run(
        [sys.executable, "-m", "rsvo_ros.ros.latency", "--frames", "3", "--resolution",
         "64x48", "--wait", "2", "--json", str(out)],
        env=ros_test_env(ros_domain(offset=7)), capture_output=True, text=True, timeout=120)
    assert proc.returncode == 2, proc.stderr
    assert "no node subscribed to /camera/image_raw" in proc.stderr
    assert "start rsvo_node first" in proc.stderr
    assert not out.exists()


@pytest.mark.parametrize("bad", ["1280-720", "0x480", "x"])
def test_a_bad_resolution_is_a_usage_error_before_ros_starts(bad, capsys):
    """The probe's --resolution is the tools' (rsvo_synth's) parser: a malformed or empty size
    is refused by argparse (exit 2, the expected form named), not a traceback later or a probe
    of 0-pixel images."""
    from rsvo_ros.ros.latency import main

    with pytest.raises(SystemExit) as exc:
        main(["--resolution", bad, "--frames", "2"])
    assert exc.value.code == 2
    assert "WIDTHxHEIGHT in positive whole numbers" in capsys.readouterr().err


def test_the_frames_as_sent_replay_as_the_pipeline_ran_on_them(tmp_path):
    """``--bag``: the probe's frames with the stamps it sent them at (a wall clock's, not the
    rendering's), their camera info, ground truth and line delay as a rosbag2 that
    rsvo_replay reads; replayed, its poses are the pipeline's on those frames and stamps."""
    from rsvo_ros.odometry.pipeline import OdometryPipeline, PipelineOptions
    from rsvo_ros.ros.bagio import custom_data
    from rsvo_ros.ros.latency import write_sent_bag
    from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig
    from rsvo_ros.tools.compare import read_tum
    from rsvo_ros.tools.replay import main as replay_main

    cfg = SynthConfig(frames=24, motion="walk", width=320, height=240, seed=3)
    renderer = SequenceRenderer(cfg)
    frames = list(renderer)
    rng = np.random.default_rng(0)  # a live sender's stamps: the interval with jitter
    stamps = [1_000_000_000_000 + round((k / cfg.rate_hz + rng.uniform(0, 3e-3)) * 1e9)
              for k in range(len(frames))]
    bag = tmp_path / "sent"
    write_sent_bag(bag, stamps, [f.image.tobytes() for f in frames], renderer.K, 320, 240,
                   [(f.R_world_cam, f.p_world_cam) for f in frames], cfg.tau)
    assert float(custom_data(bag)["rsvo.line_delay"]) == pytest.approx(cfg.tau)
    out = tmp_path / "replay"
    assert replay_main([str(bag), "--output", str(out), "--no-progress"]) == 0
    replayed = read_tum(out / "trajectory.tum")
    pipe = OdometryPipeline(renderer.K, None, cfg.tau, PipelineOptions())
    direct = {s: pipe.process(s, f.image).T_world_cam for s, f in zip(stamps, frames,
                                                                       strict=True)}
    pipe.close()
    posed = {s: T for s, T in direct.items() if T is not None}
    assert len(posed) >= 20 and sorted(replayed) == sorted(posed)
    for s, T in posed.items():
        assert np.allclose(replayed[s][:3, 3], T[:3, 3], atol=1e-6), s
    with pytest.raises(ValueError, match="one of each per frame"):
        write_sent_bag(tmp_path / "short", stamps[:3], [], renderer.K, 320, 240, [], cfg.tau)
