"""Feature tracking and the odometry pipeline (pure Python, no ROS)."""

from __future__ import annotations

import cv2
import numpy as np
import pytest
from conftest import ground_truth_pose

from rsvo_ros.core.geometry import rotation_angle_deg
from rsvo_ros.core.lens import undistort_points
from rsvo_ros.odometry.pipeline import OdometryPipeline, PipelineOptions
from rsvo_ros.odometry.tracker import (
    AUTO_BUSY_SHARE,
    AUTO_DROP_SHARE,
    AUTO_SETTLE_IMAGES,
    AUTO_SPAN_IMAGES,
    PROBE_FAILS_BELOW,
    PROBE_FEATURES,
    AutoDecimation,
    FeatureTracker,
    TrackerOptions,
    global_shift,
)
from rsvo_ros.sim.synth import SequenceRenderer, SynthConfig, intrinsics, render_sequence
from rsvo_ros.tools.replay import accuracy


@pytest.fixture(scope="module")
def textured():
    return render_sequence(SynthConfig(frames=1, width=320, height=180))[0].image


def test_tracker_follows_a_known_shift_and_spreads_features(textured):
    shifted = np.roll(textured, (2, 3), axis=(0, 1))  # 3 px right, 2 px down
    tracker = FeatureTracker(TrackerOptions(max_features=200, grid=(4, 3)))
    first = tracker.track(textured)
    assert len(first.ids) == 0 and tracker.num_tracks > 100
    pair = tracker.track(shifted)
    inner = (pair.pts_prev[:, 0] > 10) & (pair.pts_prev[:, 1] > 10)
    assert inner.sum() > 80
    flow = pair.pts_curr[inner] - pair.pts_prev[inner]
    assert np.allclose(np.median(flow, axis=0), [3.0, 2.0], atol=0.05)
    cells = np.histogram2d(pair.pts_prev[:, 0], pair.pts_prev[:, 1], bins=(4, 3),
                           range=[[0, 320], [0, 180]])[0]
    assert cells.min() > 0


def _brighter(img: np.ndarray, gain: float, offset: float) -> np.ndarray:
    return np.clip(img.astype(float) * gain + offset + 0.5, 0, 255).astype(np.uint8)


@pytest.mark.parametrize("gain, offset", [(1.25, 8.0), (0.7, -5.0)])
def test_tracks_survive_an_auto_exposure_step(textured, gain, offset):
    # an auto exposure step between two frames: KLT's squared grey-level differences lose
    # tracks or pull them off; mapped back into the previous image's levels the shift is found
    # as without the step
    shifted = _brighter(np.roll(textured, (2, 3), axis=(0, 1)), gain, offset)
    result = {}
    for on in (True, False):
        tracker = FeatureTracker(TrackerOptions(max_features=200, grid=(4, 3),
                                                photometric_compensation=on))
        tracker.track(textured)
        pair = tracker.track(shifted)
        inner = (pair.pts_prev[:, 0] > 10) & (pair.pts_prev[:, 1] > 10)
        err = np.linalg.norm(pair.pts_curr[inner] - pair.pts_prev[inner] - [3.0, 2.0], axis=1)
        result[on] = (int(np.sum(err < 0.1)), tracker.last_photometric)
    (kept_on, change), (kept_off, none) = result[True], result[False]
    assert change is not None and none is None
    # the fitted change maps grey levels as the step did (the clipped highlights aside)
    levels = np.array([60.0, 160.0])
    assert np.allclose(change[0] * levels + change[1], gain * levels + offset, atol=8.0), result
    assert kept_on > 100 and kept_on > 1.3 * kept_off, result


def test_the_photometric_check_leaves_constant_brightness_alone(textured):
    shifted = np.roll(textured, (2, 3), axis=(0, 1))
    noisy = _brighter(shifted, 1.0, 0.0) + np.random.default_rng(0).integers(
        0, 2, shifted.shape, dtype=np.uint8)  # a grey level of noise
    for img in (shifted, noisy):
        tracker = FeatureTracker(TrackerOptions(max_features=200, grid=(4, 3)))
        tracker.track(textured)
        tracker.track(img)
        assert tracker.last_photometric is None


@pytest.fixture(scope="module")
def wide():
    return render_sequence(SynthConfig(frames=1, width=1280, height=360))[0].image


def _pan_with_a_dropped_frame(wide, options, stamps=True):
    """A pan of 40 px per frame (1/30 s); the third image comes two intervals later."""
    tracker = FeatureTracker(options)
    dt = 33_333_333
    tracker.track(wide[:, 0:480].copy(), 0 if stamps else None)
    tracker.track(wide[:, 40:520].copy(), dt if stamps else None)
    pair = tracker.track(wide[:, 120:600].copy(), 3 * dt if stamps else None)
    return pair, np.abs(pair.pts_prev[:, 0] - pair.pts_curr[:, 0] - 80.0) < 1.0


def test_the_flow_prediction_keeps_a_fast_pan_across_a_dropped_frame(wide):
    # 80 px in one step is beyond KLT's reach from no motion; from each track's last motion
    # at the same rate it is a few pixels. The README's 30 Hz 1280x720 runs lost the map at
    # the fast turn this way. (The prediction alone: the re-tracking from the images' shift,
    # tested below, would rescue this pan too)
    options = TrackerOptions(max_features=200, shift_retry=False)
    pair, right = _pan_with_a_dropped_frame(wide, options)
    assert right.sum() >= 120 and right.mean() > 0.95, (len(right), right.sum())
    off = TrackerOptions(max_features=200, predict_flow=False, shift_retry=False)
    _, right_off = _pan_with_a_dropped_frame(wide, off)
    assert right_off.sum() < 60, right_off.sum()
    # without stamps there is nothing to scale the motion by: no prediction
    _, right_nostamp = _pan_with_a_dropped_frame(wide, options, stamps=False)
    assert right_nostamp.sum() == right_off.sum()
    # a pause (more than MAX_PREDICTION_RATIO intervals) is not a pan at the same rate; two
    # intervals after a pan of 40 px per interval (the image moving left): 80 px
    assert FeatureTracker(options)._predicted_motion(1.0) is None
    tracker = FeatureTracker(options)
    for k in range(2):
        tracker.track(wide[:, 40 * k:40 * k + 480].copy(), k * 33_333_333)
    assert np.allclose(np.median(tracker._predicted_motion(2 / 30)[:, 0], axis=0), [-80, 0],
                       atol=1.0)
    assert tracker._predicted_motion(1.0) is None and tracker._predicted_motion(1 / 30) is None
    # between consecutive frames (no gap) KLT starts from no motion, with or without it
    tracks = []
    for opts in (options, off):
        tracker = FeatureTracker(opts)
        for k in range(4):
            pair = tracker.track(wide[:, 20 * k:20 * k + 480].copy(), k * 33_333_333)
        tracks.append(pair.pts_curr)
    assert len(tracks[0]) > 100 and np.array_equal(tracks[0], tracks[1])


def test_the_global_shift_is_measured_by_phase_correlation(wide):
    # the content moves 150 px left and 7 px up (measured on copies averaged down to ~320 px)
    shift = global_shift(wide[0:300, 0:480], wide[7:307, 150:630])
    assert shift is not None and np.allclose(shift, (-150.0, -7.0), atol=2.0), shift
    assert global_shift(wide[0:300, 0:480], wide[0:300, 0:480]) == pytest.approx((0.0, 0.0),
                                                                             abs=0.5)
    assert global_shift(wide[:6, :6], wide[:6, :6], side_px=2) is None  # too small to measure


def _turn(wide, shift_px, retry):
    """Two consecutive frames (1/30 s apart, so no flow prediction) of a pan of ``shift_px``."""
    tracker = FeatureTracker(TrackerOptions(max_features=200, shift_retry=retry))
    tracker.track(wide[:, 0:480].copy(), 0)
    pair = tracker.track(wide[:, shift_px:shift_px + 480].copy(), 33_333_333)
    return tracker, pair, np.abs(pair.pts_curr[:, 0] - pair.pts_prev[:, 0] + shift_px) < 1.0


def test_a_turn_past_klts_reach_is_tracked_again_from_the_images_shift(wide):
    # 150 px between consecutive frames (a head turn at 15 Hz moved 1280x720 images 150-240
    # px): KLT from no motion keeps almost nothing; from the images' shift, the tracks that
    # stay in view, each moved by the pan
    tracker, pair, right = _turn(wide, 150, True)
    assert right.sum() >= 100 and right.mean() > 0.95, (len(right), right.sum())
    assert tracker.last_shift is not None and abs(tracker.last_shift[0] + 150.0) < 4.0
    _, pair_off, right_off = _turn(wide, 150, False)
    assert right_off.sum() < 30, right_off.sum()
    # within KLT's reach nothing is tracked again: the same tracks, bit for bit
    tracker, pair, _ = _turn(wide, 20, True)
    _, pair_off, _ = _turn(wide, 20, False)
    assert tracker.last_shift is None and len(pair.ids) > 100
    assert np.array_equal(pair.pts_curr, pair_off.pts_curr)
    assert np.array_equal(pair.ids, pair_off.ids)
    # the pipeline says which frames were tracked from the shift (counted by the node and the
    # replay)
    pipe = OdometryPipeline(intrinsics(480, 360), None, 0.0, PipelineOptions(model="gs"))
    results = [pipe.process(k * 33_333_333, wide[:, x:x + 480].copy())
               for k, x in enumerate((0, 150, 160))]
    assert [r.image_shift is not None for r in results] == [False, True, False]
    assert abs(results[1].image_shift[0] + 150.0) < 4.0


def _counted_klt(tracker):
    """Records ``tracker``'s KLT passes (photometric rounds included) in ``calls``: the number
    of features each was tried on."""
    calls = []
    klt = tracker._klt

    def counted(prev, img, guess, subset=None):
        calls.append(len(tracker._pts) if subset is None else len(subset))
        return klt(prev, img, guess, subset)

    tracker._klt = counted
    return calls


def test_a_turns_failed_klt_pass_is_skipped_where_a_probe_shows_it_would_fail(wide,
                                                                               monkeypatch):
    # a pan of 150 px per frame (past KLT's reach) in 640-px images: the first such frame
    # needs two full passes (KLT from no motion, which fails, then from the shift); in the
    # frames after it KLT from no motion is tried on PROBE_FEATURES features first, fails
    # there, and only the pass from the shift is made in full (constant brightness: no
    # photometric rounds to count)
    options = TrackerOptions(max_features=200, photometric_compensation=False)
    runs = {}
    for skip in (True, False):
        if not skip:  # the same frames with every probe saying "KLT alone may keep them"
            monkeypatch.setattr(FeatureTracker, "_klt_alone_fails", lambda self, img: False)
        tracker = FeatureTracker(options)
        calls = _counted_klt(tracker)
        tracker.track(wide[:, 0:640].copy(), 0)
        passes, pairs = [], []
        for k, x in enumerate((150, 300, 450), start=1):
            before = len(calls)
            pairs.append(tracker.track(wide[:, x:x + 640].copy(), k * 33_333_333))
            passes.append(calls[before:])
            assert tracker.last_shift is not None and abs(tracker.last_shift[0] + 150.0) < 4.0
        runs[skip] = (passes, pairs, tracker, calls)
    (passes, pairs, tracker, calls), (passes_all, pairs_all, _, _) = runs[True], runs[False]
    assert all(len(p) == 2 and min(p) > PROBE_FEATURES for p in passes_all), passes_all
    assert len(passes[0]) == 2 and min(passes[0]) > PROBE_FEATURES  # no turn before it
    for p in passes[1:]:
        assert p[0] == PROBE_FEATURES and len(p) == 2 and p[1] > PROBE_FEATURES, passes
    for pair, pair_all in zip(pairs, pairs_all, strict=True):  # the same tracks, to the bit
        assert np.array_equal(pair.pts_curr, pair_all.pts_curr)
        assert np.array_equal(pair.ids, pair_all.ids)
        moved = np.abs(pair.pts_curr[:, 0] - pair.pts_prev[:, 0] + 150.0) < 1.0
        assert moved.sum() >= 100 and moved.mean() > 0.95
    monkeypatch.undo()
    # the turn slows to within KLT's reach (20 px, under two windows): no probe, KLT alone
    before = len(calls)
    pair = tracker.track(wide[:, 470:1110].copy(), 4 * 33_333_333)
    assert len(calls) - before == 1 and calls[-1] > PROBE_FEATURES
    assert tracker.last_shift is None
    assert np.median(pair.pts_curr[:, 0] - pair.pts_prev[:, 0]) == pytest.approx(-20.0, abs=0.2)
    # a shift measured wrong (150 px where the image moved 20): the probe keeps its tracks,
    # so KLT alone is tried in full first and kept, as without the probe
    tracker = FeatureTracker(options)
    tracker.track(wide[:, 0:640].copy(), 0)
    tracker.track(wide[:, 150:790].copy(), 33_333_333)
    assert tracker.last_shift is not None
    monkeypatch.setattr("rsvo_ros.odometry.tracker.global_shift", lambda a, b: (150.0, 0.0))
    calls = _counted_klt(tracker)
    pair = tracker.track(wide[:, 170:810].copy(), 2 * 33_333_333)
    assert calls[0] == PROBE_FEATURES and len(calls) == 2 and tracker.last_shift is None
    assert np.median(pair.pts_curr[:, 0] - pair.pts_prev[:, 0]) == pytest.approx(-20.0, abs=0.2)
    # and where a probe said "fails" but the pass from the (wrong) shift keeps few tracks,
    # KLT from no motion is made in full as well, and kept for keeping more
    monkeypatch.setattr(FeatureTracker, "_klt_alone_fails", lambda self, img: True)
    tracker = FeatureTracker(options)
    tracker.track(wide[:, 0:640].copy(), 0)
    monkeypatch.setattr("rsvo_ros.odometry.tracker.global_shift", lambda a, b: (-150.0, 0.0))
    tracker.track(wide[:, 150:790].copy(), 33_333_333)
    assert tracker.last_shift is not None
    monkeypatch.setattr("rsvo_ros.odometry.tracker.global_shift", lambda a, b: (150.0, 0.0))
    calls = _counted_klt(tracker)
    pair = tracker.track(wide[:, 170:810].copy(), 2 * 33_333_333)
    assert len(calls) == 2 and min(calls) > PROBE_FEATURES and tracker.last_shift is None
    assert np.median(pair.pts_curr[:, 0] - pair.pts_prev[:, 0]) == pytest.approx(-20.0, abs=0.2)


@pytest.mark.parametrize("still_rows, fails", [(0.45, True), (0.75, False)])
def test_the_probe_reads_the_share_the_full_klt_pass_would_keep(wide, still_rows, fails):
    # the top rows of the next image stay where they were, the rest moved 150 px (past KLT's
    # reach): KLT from no motion keeps about the still share of the features; the probe's
    # PROBE_FEATURES read the same share, and it says "fails" below PROBE_FAILS_BELOW (0.55)
    prev = wide[:, 0:640].copy()
    img = wide[:, 150:790].copy()
    cut = int(still_rows * len(img))
    img[:cut] = prev[:cut]
    tracker = FeatureTracker(TrackerOptions(max_features=200, photometric_compensation=False))
    tracker.track(prev, 0)
    assert tracker.num_tracks >= 2 * PROBE_FEATURES
    _, good = tracker._klt(prev, img, None)
    subset = np.linspace(0, tracker.num_tracks - 1, PROBE_FEATURES).round().astype(np.int64)
    _, probe = tracker._klt(prev, img, None, subset)
    assert abs(good.mean() - still_rows) < 0.1
    assert abs(probe.mean() - good.mean()) < 0.1
    assert (probe.mean() < PROBE_FAILS_BELOW) == fails
    assert tracker._klt_alone_fails(img) == fails


@pytest.mark.slow
def test_a_15_hz_walk_keeps_its_map_through_the_look_around():
    """A walk seen by a 15 Hz camera (seed 100, 150 frames, 640x360): in the stop-and-look the
    image moves past KLT's reach between frames. KLT alone lost its tracks there and 7 frames
    were held (ATE 0.46 m); re-tracked from the images' shift, every frame is posed (ATE
    0.06 m, measured)."""
    cfg = SynthConfig(frames=150, motion="walk", severity=0.7, seed=100, frame_rate=15.0)
    runs = {}
    for retry in (True, False):
        renderer = SequenceRenderer(cfg)
        options = PipelineOptions()
        options.tracker.shift_retry = retry
        pipe = OdometryPipeline(renderer.K, None, cfg.tau, options)
        gt, est, held, shifted = {}, {}, 0, 0
        for frame in renderer:
            stamp = round(frame.stamp * 1e9)
            res = pipe.process(stamp, frame.image)
            gt[stamp], est[stamp] = frame.pose(), res.T_world_cam
            held += res.status == "held"
            shifted += res.image_shift is not None
        pipe.close()
        runs[retry] = (accuracy(gt, est)["ate_m"]["rmse"], held, shifted)
    (ate_on, held_on, shifted_on), (ate_off, held_off, shifted_off) = runs[True], runs[False]
    assert held_on == 0 and shifted_on > 0 and shifted_off == 0
    assert held_off > 0 and ate_on < 0.5 * ate_off, runs


def test_tracker_redetects_when_tracks_are_lost(textured):
    tracker = FeatureTracker(TrackerOptions(max_features=150))
    tracker.track(textured)
    lost = tracker.track(np.full_like(textured, 128))  # a blank frame: nothing to track
    assert len(lost.ids) == 0
    tracker.track(textured)
    assert tracker.num_tracks > 50


def test_undistort_points_inverts_plumb_bob():
    K = np.array([[400.0, 0, 160], [0, 400.0, 90], [0, 0, 1]])
    D = np.array([-0.2, 0.05, 0.001, -0.001, 0.0])
    pts = np.array([[10.0, 10.0], [160.0, 90.0], [300.0, 170.0]])
    rays = np.column_stack([(pts - K[:2, 2]) / 400.0, np.ones(3)])
    distorted, _ = cv2.projectPoints(rays, np.zeros(3), np.zeros(3), K, D)
    assert np.allclose(undistort_points(distorted.reshape(-1, 2), K, D), pts, atol=1e-3)
    assert np.array_equal(undistort_points(pts, K, None), pts)


def _run(cfg, model="gs", frames=None, backend="window"):
    renderer = SequenceRenderer(cfg)
    pipe = OdometryPipeline(renderer.K, None, cfg.tau, PipelineOptions(model=model,
                                                                      backend=backend))
    out = []
    for fr in renderer:
        img = fr.image if frames is None else frames(fr)
        out.append((fr, pipe.process(round(fr.stamp * 1e9), img)))
    return pipe, out


@pytest.fixture(scope="module")
def forward_drive():
    """60 frames of a global-shutter vehicle driving straight on, without shake: the image
    grows from frame to frame and nothing else should change the scale."""
    return render_sequence(SynthConfig(frames=60, motion="vehicle", severity=0.0,
                                       line_delay=0.0, seed=0))


def _drive_accuracy(frames, refine_window_px):
    tracker = TrackerOptions(refine_window_px=refine_window_px)
    pipe = OdometryPipeline(intrinsics(frames[0].image.shape[1], frames[0].image.shape[0]),
                            None, 0.0, PipelineOptions(model="gs", tracker=tracker))
    est, gt = {}, {}
    for fr in frames:
        stamp = round(fr.stamp * 1e9)
        est[stamp] = pipe.process(stamp, fr.image).T_world_cam
        gt[stamp] = ground_truth_pose(fr)
    return accuracy(gt, est)


def test_refined_tracks_keep_a_forward_drive_at_its_scale(forward_drive):
    """The window backend's vehicles shrank by 1.2-2 %/s on this drive with the 21-px KLT
    alone (each track lags behind the growing image); the small-window refinement, on by
    default, holds the scale (measured: -1.8 -> -0.2 %/s, ATE 0.020 -> 0.004 m, seed 0; seeds
    1-3 alike). The companion run without it shows the check can fail."""
    refined = _drive_accuracy(forward_drive, None)
    assert abs(refined["scale_rate"]["percent_per_s"]) < 0.6
    assert refined["ate_m"]["rmse"] < 0.01
    plain = _drive_accuracy(forward_drive, 0)
    assert plain["scale_rate"]["percent_per_s"] < -1.0
    assert plain["ate_m"]["rmse"] > 2 * refined["ate_m"]["rmse"]


def test_a_refinement_that_would_jump_keeps_the_pyramids_position(textured):
    """The refinement only polishes: a point it would move by the forward-backward threshold
    or more keeps the pyramid's result, so the refinement cannot add a gross error. An
    8-px window on a shifted copy agrees with the 21-px track within a tenth of a pixel."""
    shifted = np.roll(textured, (2, 3), axis=(0, 1))
    tracks = {}
    for refine in (0, 8):
        tracker = FeatureTracker(TrackerOptions(max_features=200, grid=(4, 3),
                                                refine_window_px=refine))
        tracker.track(textured)
        pair = tracker.track(shifted)
        tracks[refine] = dict(zip(pair.ids.tolist(), pair.pts_curr, strict=True))
    assert tracks[0].keys() == tracks[8].keys()  # the same tracks survive
    moved = np.array([np.linalg.norm(tracks[8][i] - tracks[0][i]) for i in tracks[0]])
    assert moved.max() < 1.0 and np.median(moved) < 0.1
    for bad in (1, 2, 99, -1):
        with pytest.raises(ValueError, match="refine_window_px"):
            FeatureTracker(TrackerOptions(refine_window_px=bad))
    for bad in (4, 52, 0, 17.5, True, None, float("nan"), "17"):
        with pytest.raises(ValueError, match="window_px must be 5-51"):
            FeatureTracker(TrackerOptions(window_px=bad))


def test_decimated_tracking_hands_on_full_resolution_pixels():
    """With decimation 2 the tracker detects and tracks in the image averaged down to half its
    size and returns full-resolution pixels: a 6 x 4 px shift of a 640x360 image comes out as
    6 x 4 px (3 x 2 in the reduced image), with features over the whole image."""
    image = render_sequence(SynthConfig(frames=1, width=640, height=360))[0].image
    shifted = np.roll(image, (4, 6), axis=(0, 1))
    tracker = FeatureTracker(TrackerOptions(max_features=200, grid=(4, 3), decimation=2))
    tracker.track(image)
    ids, pts = tracker.current()
    assert len(ids) > 100 and pts[:, 0].max() > 500 and pts[:, 1].max() > 270
    pair = tracker.track(shifted)
    inner = (pair.pts_prev[:, 0] > 20) & (pair.pts_prev[:, 1] > 20)
    assert inner.sum() > 80
    flow = pair.pts_curr[inner] - pair.pts_prev[inner]
    assert np.allclose(np.median(flow, axis=0), [6.0, 4.0], atol=0.1)
    ids_now, pts_now = tracker.current()
    now = dict(zip(ids_now.tolist(), pts_now, strict=True))
    assert all(np.array_equal(now[i], q) for i, q in zip(pair.ids.tolist(), pair.pts_curr,
                                                          strict=True))
    for bad in (0, 5, -1, 1.5, True, None, "2"):
        with pytest.raises(ValueError, match="decimation must be an integer 1-4"):
            FeatureTracker(TrackerOptions(decimation=bad))


@pytest.mark.parametrize("old, new", [(1, 2), (2, 1), (2, 3)])
def test_a_tracker_changes_its_decimation_without_losing_tracks(old, new):
    """set_decimation between two images: every track of the image before goes on into the
    next one at the new resolution (same ids, the 6 x 4 px shift in full-resolution pixels),
    where a tracker that forgot the previous image's resolution would lose them all."""
    image = render_sequence(SynthConfig(frames=1, width=640, height=360))[0].image
    shifted = np.roll(image, (4, 6), axis=(0, 1))
    tracker = FeatureTracker(TrackerOptions(max_features=200, grid=(4, 3), decimation=old))
    tracker.track(image)
    ids_before, pts_before = tracker.current()
    tracker.set_decimation(new)
    assert tracker.options.decimation == new
    ids_carried, pts_carried = tracker.current()  # the same features, in full-res pixels
    assert np.array_equal(ids_carried, ids_before)
    assert np.allclose(pts_carried, pts_before, atol=1e-3)
    pair = tracker.track(shifted)
    inner = (pair.pts_prev[:, 0] > 30) & (pair.pts_prev[:, 1] > 30)
    assert inner.sum() > 0.6 * len(ids_before)
    assert set(pair.ids.tolist()) <= set(ids_before.tolist())
    flow = pair.pts_curr[inner] - pair.pts_prev[inner]
    assert np.allclose(np.median(flow, axis=0), [6.0, 4.0], atol=0.15)
    with pytest.raises(ValueError, match="decimation must be an integer 1-4"):
        tracker.set_decimation(5)


def test_auto_decimation_steps_down_after_a_span_with_too_many_drops_or_no_headroom():
    """AutoDecimation: nothing judged before AUTO_SETTLE_IMAGES; then a span of
    AUTO_SPAN_IMAGES received images with more than AUTO_DROP_SHARE dropped, or during which
    processing took more than AUTO_BUSY_SHARE of the time, steps the decimation up by one,
    while the reduced image's longer side stays >= 480 px: a 1280x720 camera goes to 2 and
    stays there, a 640x480 one stays at 1, a 1920x1080 one goes on to 4."""
    settle, span = AUTO_SETTLE_IMAGES, AUTO_SPAN_IMAGES
    few = int(AUTO_DROP_SHARE * span)  # at the share: not more than it
    idle = 0.5 * AUTO_BUSY_SHARE  # busy seconds per second of a node with headroom
    hd = (1280, 720)
    auto = AutoDecimation()
    # the start-up's drops and load do not count; the first span starts at `settle`
    assert auto.update(settle - 1, settle - 1, 10.0, 10.0, hd) is None
    assert auto.update(settle, settle, 10.0, 10.0, hd) is None
    assert auto.update(settle + span - 1, settle + span, 10.0, 11.0, hd) is None  # not whole
    t = 10.0 + span / 30.0
    assert auto.update(settle + span, settle + few, 10.0 + idle * (t - 10.0), t, hd) is None
    t2 = t + span / 30.0
    step = auto.update(settle + 2 * span, settle + 2 * few + 1, 10.0 + idle * (t2 - 10.0), t2,
                       hd)
    assert step is not None and (step.factor, step.previous) == (2, 1) and auto.factor == 2
    assert (step.received, step.dropped) == (span, few + 1)
    assert f"dropped {few + 1} of the last {span} images" in step.describe()
    assert auto.update(settle + 3 * span, settle + 3 * span, 0.0, t2 + 2.0, hd) is None
    assert auto.factor == 2  # 1280 / 3 < 480
    vga = AutoDecimation()
    assert vga.update(settle, 0, 0.0, 0.0, (640, 480)) is None
    assert vga.update(settle + span, span, 2.0, 2.0, (640, 480)) is None and vga.factor == 1
    # no image dropped, but busy 90 % of the time: no headroom, steps; 60 %: kept
    for share, steps in ((0.9, True), (0.6, False)):
        busy = AutoDecimation(settle=0)
        assert busy.update(0, 0, 0.0, 0.0, hd) is None
        step = busy.update(span, 0, share * 2.0, 2.0, hd)
        assert (step is not None) == steps and busy.factor == (2 if steps else 1)
        if steps:
            assert step.dropped == 0 and "busy 90 % of the time" in step.describe()
    full_hd = AutoDecimation(start=2, settle=0)
    factors = [full_hd.update(n * span, n * span // 2, 0.0, float(n), (1920, 1080))
               for n in range(5)]
    assert [s.factor for s in factors if s is not None] == [3, 4]  # 1920 / 4 = 480: the last
    with pytest.raises(ValueError, match="start must be an integer 1-4"):
        AutoDecimation(start=0)
    with pytest.raises(ValueError, match="span >= 1"):
        AutoDecimation(span=0)


def test_the_pipeline_tracks_at_half_resolution_and_skips_too_small_images():
    """A 640x360 walk tracked at decimation 2 is posed on every frame as well as at full
    resolution (the camera model and the readout rows stay the full image's; measured: per-frame
    rotation error 0.263 against 0.258 deg, ATE 0.044 against 0.066 m; with the tracks left in
    the reduced image's pixels 1.008 deg); an image too small to track at the decimation is a
    skipped frame that says why, and the next frame is posed."""
    cfg = SynthConfig(frames=20, motion="walk", severity=1.0, width=640, height=360, seed=3)
    frames = render_sequence(cfg)
    errors = {}
    for factor in (1, 2):
        pipe = OdometryPipeline(intrinsics(640, 360), None, cfg.tau, PipelineOptions(
            tracker=TrackerOptions(decimation=factor)))
        est, gt = {}, {}
        for k, fr in enumerate(frames):
            stamp = round(fr.stamp * 1e9)
            if factor == 2 and k == 10:
                small = pipe.process(stamp - 1000, np.zeros((30, 40), np.uint8))
                assert small.status == "skipped" and "too small" in small.reason
                assert "decimation 2" in small.reason
            res = pipe.process(stamp, fr.image)
            assert res.status == ("first" if k == 0 else "posed"), (factor, k, res.reason)
            est[stamp], gt[stamp] = res.T_world_cam, ground_truth_pose(fr)
        errors[factor] = accuracy(gt, est)
    rpe = {f: a["rpe_rot_deg"]["rmse"] for f, a in errors.items()}
    assert rpe[2] < 1.25 * rpe[1], rpe
    assert errors[2]["ate_m"]["rmse"] < 2.0 * errors[1]["ate_m"]["rmse"]


def _first_step_errors(cfg, frames, **options):
    """Each frame's rotation error against the previous frame, and the direction error of its
    step (row 0 to row 0, in the previous camera), in degrees."""
    pipe = OdometryPipeline(intrinsics(cfg.width, cfg.height), None, cfg.tau,
                            PipelineOptions(**options))  # fmt: skip
    T = [pipe.process(round(fr.stamp * 1e9), fr.image).T_world_cam for fr in frames]
    rot = np.array([rotation_angle_deg((a.R_world_cam.T @ b.R_world_cam).T
                                       @ (Ta[:3, :3].T @ Tb[:3, :3]))
                    for a, b, Ta, Tb in zip(frames, frames[1:], T, T[1:], strict=False)])
    steps = [(a.R_world_cam.T @ (b.p_world_cam - a.p_world_cam), Ta[:3, :3].T @ (Tb[:3, 3]
              - Ta[:3, 3])) for a, b, Ta, Tb in zip(frames, frames[1:], T, T[1:], strict=False)]
    direction = np.array([np.degrees(np.arccos(np.clip(g @ e / np.linalg.norm(g)
                                                       / np.linalg.norm(e), -1, 1)))
                          for g, e in steps])  # fmt: skip
    return rot, direction


def test_an_uncertain_pair_rotation_is_taken_from_a_turning_camera(monkeypatch):
    """The first pairs of a shaken RS vehicle, posed by the chain before the window's map
    starts: on this one the pair estimator's first rotation was 7 deg off (true 1.3 deg; its
    own rotation std 3.5 deg) and the next three 2-4 deg, as the error was the next pairs'
    start. With a turning camera's rotation for pairs whose rotation std is over
    BOOTSTRAP_UNCERTAIN_ROTATION_DEG (the default) every frame is within 0.7 deg; at 1 deg
    (the previous rule) within 1.1 deg; never (0), the check fails. The turning camera's
    direction of pairs 2 and 3 left a third of the tracks behind a camera and was 86-124 deg
    off; the last pair's direction is kept there (UNCERTAIN_MIN_FRONT): every step of the
    first four within 15 deg, against up to 103 deg without."""
    from rsvo_ros.odometry import pairwise

    cfg = SynthConfig(frames=6, motion="vehicle", severity=2.0, seed=10)
    frames = render_sequence(cfg)
    rot, direction = _first_step_errors(cfg, frames)
    assert rot.max() < 0.7
    assert direction[:4].max() < 15.0, direction
    assert _first_step_errors(cfg, frames, uncertain_rotation_deg=1.0)[0].max() < 1.5
    assert _first_step_errors(cfg, frames, uncertain_rotation_deg=0.0)[0].max() > 4.0
    monkeypatch.setattr(pairwise, "UNCERTAIN_MIN_FRONT", 0.0)
    assert _first_step_errors(cfg, frames)[1][:4].max() > 45.0


@pytest.mark.parametrize("backend", ["window", "pairwise"])
def test_pipeline_poses_every_frame_of_a_clean_sequence(backend):
    cfg = SynthConfig(frames=6, motion="vehicle", severity=0.0, width=640, height=360,
                      line_delay=0.0)
    _, out = _run(cfg, backend=backend)
    assert [r.status for _, r in out] == ["first"] + ["posed"] * 5
    for (fr0, r0), (fr1, r1) in zip(out[:-1], out[1:], strict=True):
        assert np.isfinite(r1.T_world_cam).all()
        R_gt = fr1.R_world_cam.T @ fr0.R_world_cam
        R_est = r1.T_world_cam[:3, :3].T @ r0.T_world_cam[:3, :3]
        assert rotation_angle_deg(R_gt @ R_est.T) < 1.0
    # the estimated motion points the way the camera drove (up to the monocular scale)
    T0, T5 = out[0][1].T_world_cam, out[-1][1].T_world_cam
    d_est = T0[:3, :3].T @ (T5[:3, 3] - T0[:3, 3])
    d_gt = out[0][0].R_world_cam.T @ (out[-1][0].p_world_cam - out[0][0].p_world_cam)
    cos = d_est @ d_gt / np.linalg.norm(d_est) / np.linalg.norm(d_gt)
    assert cos > 0.97
    traces = [np.trace(r.covariance) for _, r in out]
    if backend == "pairwise":  # the chain's uncertainty grows; the window's is per frame
        assert all(b >= a for a, b in zip(traces, traces[1:], strict=False))
    assert all(np.isfinite(t) and t > 0 for t in traces[1:])
    # every posed frame says which of its drawn tracks the estimate used (the debug image):
    # the pairwise start, the map's initialisation and the frames tracked against the map
    for _, r in out[1:]:
        assert 0.5 < r.inlier_ratio <= 1.0, (r.reason, r.inlier_ratio)
        assert r.inliers is not None and len(r.inliers) == len(r.pts_curr), r.reason
        assert r.inliers.sum() > 0.5 * len(r.inliers), r.reason
        if r.outliers is not None:
            assert len(r.outliers) == len(r.pts_curr) and not (r.inliers & r.outliers).any()


@pytest.mark.parametrize("backend", ["window", "pairwise"])
def test_pipeline_survives_bad_frames_and_stamps(backend):
    cfg = SynthConfig(frames=8, motion="vehicle", severity=0.5, width=320, height=180)
    renderer = SequenceRenderer(cfg)
    pipe = OdometryPipeline(renderer.K, None, cfg.tau, PipelineOptions(model="gs",
                                                                      backend=backend))
    frames = list(renderer)
    stamps = [round(f.stamp * 1e9) for f in frames]
    res = [pipe.process(stamps[0], frames[0].image), pipe.process(stamps[1], frames[1].image)]
    res.append(pipe.process(stamps[1], frames[1].image))  # duplicate stamp
    res.append(pipe.process(stamps[0], frames[2].image))  # backwards
    res.append(pipe.process(stamps[2], np.zeros((180, 320), np.uint8)))  # blank frame
    res.append(pipe.process(stamps[3], np.zeros((0, 0), np.uint8)))  # empty image
    res += [pipe.process(s, f.image) for s, f in zip(stamps[4:], frames[4:], strict=True)]
    st = [r.status for r in res]
    assert st[:4] == ["first", "posed", "skipped", "skipped"]
    assert "duplicate" in res[2].reason and "backwards" in res[3].reason
    assert st[4] == "held" and "lost tracking" in res[4].reason
    assert st[5] == "skipped"
    assert "posed" in st[6:]  # it recovers
    for r in res:
        if r.has_pose:
            assert np.isfinite(r.T_world_cam).all()
    held_pose = res[4].T_world_cam
    assert np.allclose(held_pose, res[1].T_world_cam)  # no jump from a failed frame


def test_pipeline_rejects_a_bad_camera():
    with pytest.raises(ValueError, match="K"):
        OdometryPipeline(np.zeros((3, 3)), None, 0.0)
    with pytest.raises(ValueError, match="line_delay"):
        OdometryPipeline(np.eye(3), None, -1.0)


def test_scale_follows_a_camera_that_speeds_up():
    """The synthetic vehicle speeds up (its baseline grows ~10 % over these frames); the chained
    scale must follow it, not keep part of every change out (a blended scale would)."""
    cfg = SynthConfig(frames=20, motion="vehicle", severity=0.0, width=640, height=360,
                      line_delay=0.0)
    _, out = _run(cfg, model="rs")
    assert all(r.status in ("first", "posed") for _, r in out)
    p_gt = np.array([fr.p_world_cam for fr, _ in out])
    p_est = np.array([r.T_world_cam[:3, 3] for _, r in out])
    b_gt = np.linalg.norm(np.diff(p_gt, axis=0), axis=1)
    b_est = np.linalg.norm(np.diff(p_est, axis=0), axis=1)
    growth_gt = b_gt[-5:].mean() / b_gt[:5].mean()
    growth_est = b_est[-5:].mean() / b_est[:5].mean()
    assert growth_gt > 1.05
    assert growth_est == pytest.approx(growth_gt, rel=0.03)


def test_a_restarted_chain_keeps_its_baseline_near_the_one_it_restarted_with():
    """The chain bridges a lost map (the window restarts it with its last baseline). Pairs
    that keep measuring a larger scale (a stop-and-look-around: no translation to measure
    it from) grew the baseline 1.25x per pair without end, to 1e15 m in 700 frames; after a
    restart it stays within RESTART_BASELINE_RANGE of the restart's. A chain that was not
    restarted (the pairwise backend) still follows any steady change of speed."""
    from types import SimpleNamespace

    from rsvo_ros.odometry.pairwise import RESTART_BASELINE_RANGE

    def grow(chain, steps):
        ids = np.arange(20)
        for _ in range(steps):
            chain._prev_depths = {int(i): 1.0 for i in ids}
            # each pair's depths say twice the last baseline (clipped to 1.25x per pair)
            rel = SimpleNamespace(inliers=np.ones(20, bool))
            scale, _ = chain._relative_scale(ids, rel, np.full(20, 0.5 / chain._last_baseline),
                                             1.0)  # fmt: skip
            chain._last_baseline = scale
        return chain._last_baseline

    pipe = OdometryPipeline(np.array([[500.0, 0, 320], [0, 500.0, 180], [0, 0, 1]]), None, 0.0)
    pipe.chain.restart(np.eye(4), 0.05)
    assert grow(pipe.chain, 40) == pytest.approx(0.05 * RESTART_BASELINE_RANGE)
    free = OdometryPipeline(np.array([[500.0, 0, 320], [0, 500.0, 180], [0, 0, 1]]), None, 0.0)
    free.chain._last_baseline = 0.05
    assert grow(free.chain, 40) == pytest.approx(0.05 * 1.25**40)


def test_frames_dropped_by_the_caller_keep_the_stream_clock():
    """A stall: the caller drops the frames of 1.5 s (the node's newest-frame policy) and
    says so (note_dropped): the next frame, 1.5 s after the last processed one but one
    interval after the last dropped one, is processed; without the note it is skipped as
    far ahead (and logged as bad input by the node). A note about an earlier stamp, or
    before the first frame, changes nothing."""
    cfg = SynthConfig(frames=4, motion="vehicle", severity=0.5, width=320, height=180, seed=2)
    frames = render_sequence(cfg)
    K = SequenceRenderer(cfg).K
    ns = [round(f.stamp * 1e9) for f in frames]
    stall = 1_500_000_000
    results = {}
    for noted in (False, True):
        pipe = OdometryPipeline(K, None, cfg.tau, PipelineOptions(model="gs"))
        pipe.note_dropped(ns[0] - 10**9)  # before the first frame: ignored
        first = pipe.process(ns[0], frames[0].image)
        assert first.status == "first"
        if noted:
            pipe.note_dropped(ns[0] - 10**6)  # not after the last processed frame: ignored
            for k in range(1, 46):  # 45 frames of a 30 Hz stream dropped meanwhile
                pipe.note_dropped(ns[0] + k * (ns[1] - ns[0]))
        results[noted] = pipe.process(ns[1] + stall, frames[1].image)
        pipe.close()
    assert results[False].status == "skipped" and "far ahead" in results[False].reason
    assert results[True].status != "skipped"


def test_time_jumps_late_frames_far_ahead_stamps_and_pauses():
    cfg = SynthConfig(frames=8, motion="vehicle", severity=0.5, width=320, height=180, seed=2)
    frames = render_sequence(cfg)
    renderer = SequenceRenderer(cfg)
    pipe = OdometryPipeline(renderer.K, None, cfg.tau, PipelineOptions(model="gs"))
    ns = [round(f.stamp * 1e9) for f in frames]  # 33.3 ms apart
    img = [f.image for f in frames]
    out = [pipe.process(ns[k], img[k]) for k in range(4)]
    assert all(r.has_pose for r in out)
    late = pipe.process(ns[3] - 10_000_000, img[2])  # a late frame: skipped
    assert late.status == "skipped" and "backwards" in late.reason
    ahead = pipe.process(ns[4] + 500 * 10**9, img[4])  # a corrupt stamp: skipped, clock kept
    assert ahead.status == "skipped" and "far ahead" in ahead.reason
    assert pipe.process(ns[4], img[4]).status == "posed"
    # a pause: two frames agree on a time 5 s later: the stream goes on from there
    gap = 5 * 10**9
    assert pipe.process(ns[5] + gap, img[5]).status == "skipped"
    resumed = pipe.process(ns[6] + gap, img[6])
    assert resumed.status != "skipped" and not resumed.time_reset
    # time back by more than two frames: a new trajectory from the identity
    reset = pipe.process(ns[0], img[0])
    assert reset.time_reset and reset.status == "first" and "time jumped back" in reset.reason
    assert np.allclose(reset.T_world_cam, np.eye(4))
    assert pipe.process(ns[1], img[1]).has_pose
