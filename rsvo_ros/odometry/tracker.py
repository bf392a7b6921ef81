"""Feature tracking for the frame-pair pipeline: bucketed corners, pyramidal KLT with a
forward-backward check (after a dropped frame started from each track's last image motion;
where the brightness changed, in the previous image's grey levels), re-detection where tracks
thin out.

Pure numpy + OpenCV, no ROS.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

# the flow prediction is made for a gap of more than GAP_RATIO and at most MAX_PREDICTION_RATIO
# of the last image interval (a longer gap, a stall or a pause, is not a pan at the same rate)
GAP_RATIO = 1.5
MAX_PREDICTION_RATIO = 4.0
DEFAULT_MAX_FEATURES = 500  # paper, Sec. 7.1: "limited up to 500 with a bucketing strategy"
# A 21-px KLT window on an image that grows (forward motion) lets each track lag behind the
# expansion by a fraction of a pixel per frame; along a track this adds up, and the window
# backend's vehicles shrank by about 2.4 %/s. Refining with an 11-px window at full resolution
# keeps the pyramid's reach and removes most of it (docs/notebook.md, "The vehicles' scale
# shrinks")
REFINE_WINDOW_PX = 11
MAX_REFINE_WINDOW_PX = 51
# The pyramid's KLT window (px; VINS-Mono's 21). OpenCV's time per point grows with its area:
# 17 px takes 0.45-0.63x the time of 21 (640x480 and 1280x720 walks, 500 points, one or two
# threads; 13-19 px are not faster than 17) and gave the same ATE on 99 synthetic bags, but on
# the real BS-RSC pair_3 its tracks turned the RS estimate 4 deg away from the GS twins' motion
# (README, "A smaller KLT window: faster, and not kept as the default")
DEFAULT_WINDOW_PX = 21
MIN_WINDOW_PX, MAX_WINDOW_PX = 5, 51
# Tracking at a reduced resolution (rtabmap's Odom/ImageDecimation): each image is averaged
# down by this integer factor (cv2.INTER_AREA) before detection and KLT, and the tracks are
# handed on in the full image's pixels, where the camera model and the readout rows live
MAX_DECIMATION = 4
# The live node's automatic decimation (AutoDecimation; node tracking_decimation_mode: auto):
# after the first AUTO_SETTLE_IMAGES received images (the start-up: the first map), a span of
# AUTO_SPAN_IMAGES received images of which more than AUTO_DROP_SHARE were dropped, or during
# which the node was busy processing for more than AUTO_BUSY_SHARE of the time (no headroom:
# the drops come in the bursts of a look-around or a lost map), steps the decimation up by one,
# as long as the reduced image's longer side stays at least AUTO_MIN_SIDE_PX (a 640x480 camera
# stays at full resolution: there KLT's time is per point, not per pixel, and half resolution
# did not keep up either: README, "Tracking at a reduced resolution"). It never steps back
# during a run
AUTO_SETTLE_IMAGES = 30
AUTO_SPAN_IMAGES = 60
AUTO_DROP_SHARE = 0.10
AUTO_BUSY_SHARE = 0.70
AUTO_MIN_SIDE_PX = 480
# Photometric compensation (auto exposure / gain): the current image's grey levels are mapped
# into the previous image's before KLT (whose squared differences assume constant brightness)
# when the tracked points say the brightness changed by more than PHOTOMETRIC_TOLERANCE grey
# levels somewhere between the 5th and 95th percentile of their grey levels; each image starts
# from the last image's change (an auto exposure ramps over several frames). Where nothing is
# mapped the tracks are plain KLT's, bit for bit (no frame of the constant-brightness bags
# measured was mapped: README, "Auto exposure")
PHOTOMETRIC_TOLERANCE = 3.0
PHOTOMETRIC_ROUNDS = 2  # refit, map and track again at most this often per image
PHOTOMETRIC_MIN_POINTS = 20  # tracked points to fit the change; fewer: the images' own levels
PHOTOMETRIC_CLIPPED = (4, 251)  # grey levels at or beyond these are clipped (not fitted)
PHOTOMETRIC_PATCH = 7  # px: the grey level of a tracked point is its patch's mean
# Re-tracking from the image's global shift: a fast pan or head turn moves the image by more
# than the pyramid's reach (at 15 Hz the walks' look-around moves it 150-240 px between frames
# at 1280x720, and KLT kept 1-18 of 500 tracks). When KLT keeps less than RETRY_BELOW_SHARE of
# the tracks, the shift between the two images is measured by phase correlation on copies
# averaged down to about GLOBAL_SHIFT_SIDE_PX on their longer side (0.5-0.7 ms), and if it is at
# least half the KLT window, every track is tracked again from it; the attempt that keeps more
# tracks is taken. Frames where KLT keeps its tracks are tracked as before, bit for bit (README,
# "Re-tracking a fast turn from the image's shift")
RETRY_BELOW_SHARE = 0.7
GLOBAL_SHIFT_SIDE_PX = 320
# In a turn (the last image tracked from its shift) a failed first KLT pass costs 2-3 times a
# kept one (its tracks run to the iteration limit on every level). Where the image has moved
# by SHIFT_FIRST_WINDOWS KLT windows or more, KLT from no motion is first tried on
# PROBE_FEATURES features spread over the list (each feature is tracked on its own, so they
# come out as in the full pass); where under PROBE_FAILS_BELOW of them are kept, the full pass
# would keep under RETRY_BELOW_SHARE and the shift's attempt would follow anyway, so that one
# is made first and the failed pass is saved. Taking the shift's tracks where KLT alone keeps
# its own (the shift's attempt first on every such frame) made the walks 1.3x worse (README,
# "A turn's frames: the failed pass skipped"). The probe's share follows the full pass's
# closely (1280x720 15 Hz walks 0, 2108, 2110: where the probe kept under 0.55, the full pass
# kept at most 0.64; 64 features drawn at random from a true 0.70 read under 0.55 once in
# 150); at 0.55 it saves the failed pass on 43, 39, 26 of those walks' 48, 47, 36 probed frames
# (32, 37, 19 at 0.35), with the same tracks (README, "A turn's probe at 0.55")
SHIFT_FIRST_WINDOWS = 2.0
PROBE_FEATURES = 64
PROBE_FAILS_BELOW = 0.55


def check_refine_window(px: int | None, name: str = "refine_window_px",
                        default: str = "None") -> None:
    """``ValueError`` unless ``px`` is a :attr:`TrackerOptions.refine_window_px`: None (the
    default choice), 0 (off) or 3-``MAX_REFINE_WINDOW_PX``; the message names the setting
    ``name`` and spells the default choice ``default``."""
    if px is not None and px != 0 and not 3 <= px <= MAX_REFINE_WINDOW_PX:
        raise ValueError(f"{name} must be {default} (the default choice), 0 (off) or "
                         f"3-{MAX_REFINE_WINDOW_PX} px, got {px}")


def check_window(px: int, name: str = "window_px") -> None:
    """``ValueError`` unless ``px`` is a pyramid KLT window of ``MIN_WINDOW_PX``-``MAX_WINDOW_PX``
    px; the message names the setting ``name``."""
    if (isinstance(px, bool) or not isinstance(px, int | np.integer)
            or not MIN_WINDOW_PX <= px <= MAX_WINDOW_PX):
        raise ValueError(f"{name} must be {MIN_WINDOW_PX}-{MAX_WINDOW_PX} px, got {px}")


def check_decimation(factor: int, name: str = "decimation") -> None:
    """``ValueError`` unless ``factor`` is a :attr:`TrackerOptions.decimation` (an integer
    1-``MAX_DECIMATION``); the message names the setting ``name``."""
    if (isinstance(factor, bool) or not isinstance(factor, int | np.integer)
            or not 1 <= factor <= MAX_DECIMATION):
        raise ValueError(f"{name} must be an integer 1-{MAX_DECIMATION} (1: full resolution), "
                         f"got {factor}")


def decimated(img: np.ndarray, factor: int) -> np.ndarray:
    """``img`` averaged down by ``factor`` (each output pixel the mean of a ``factor`` x
    ``factor`` block; a remainder of rows or columns is dropped); ``img`` itself for 1."""
    if factor == 1:
        return img
    h, w = img.shape[:2]
    return cv2.resize(img[:h - h % factor, :w - w % factor], (w // factor, h // factor),
                      interpolation=cv2.INTER_AREA)


def to_full_resolution(pts: np.ndarray, factor: int) -> np.ndarray:
    """Pixels ``pts`` (n, 2) of an image :func:`decimated` by ``factor`` in the full image's
    pixels (pixel centres: ``(x + 0.5) factor - 0.5``)."""
    return pts if factor == 1 else (pts + 0.5) * factor - 0.5


def refine_window_or_auto(px: int, name: str) -> int | None:
    """A command line's or a ROS parameter's (``name``) refinement window (-1: the default
    choice) as :attr:`TrackerOptions.refine_window_px`; ``ValueError`` naming it otherwise."""
    window = None if px == -1 else px
    check_refine_window(window, name, "-1")
    return window


@dataclass
class DecimationStep:
    """:meth:`AutoDecimation.update`'s decision to track at ``factor`` from now on: ``dropped``
    of the last ``received`` images were dropped, and processing took ``busy_share`` of the
    time they spanned."""

    factor: int
    previous: int
    received: int
    dropped: int
    busy_share: float

    def describe(self) -> str:
        return (f"dropped {self.dropped} of the last {self.received} images "
                f"({100.0 * self.dropped / self.received:.0f} %), busy "
                f"{100.0 * self.busy_share:.0f} % of the time: tracking at 1/{self.factor} of "
                f"the resolution from now on (was 1/{self.previous})")


class AutoDecimation:
    """When a live node falls behind its camera, track at a lower resolution: fed the node's
    running counts of received and dropped images and its time spent processing, :meth:`update`
    steps the decimation up by one after a span of images with too many dropped or too little
    idle time (``AUTO_*``). Pure bookkeeping; the caller applies a step with
    :meth:`FeatureTracker.set_decimation`."""

    def __init__(self, start: int = 1, settle: int = AUTO_SETTLE_IMAGES,
                 span: int = AUTO_SPAN_IMAGES, drop_share: float = AUTO_DROP_SHARE,
                 busy_share: float = AUTO_BUSY_SHARE,
                 min_side_px: int = AUTO_MIN_SIDE_PX):  # fmt: skip
        check_decimation(start, "start")
        if span < 1 or settle < 0 or not 0.0 <= drop_share < 1.0 or not busy_share > 0.0 \
                or min_side_px < 1:  # fmt: skip
            raise ValueError(f"AutoDecimation: span >= 1, settle >= 0, 0 <= drop_share < 1, "
                             f"busy_share > 0 and min_side_px >= 1, got {span}, {settle}, "
                             f"{drop_share}, {busy_share}, {min_side_px}")
        self.factor = start
        self.settle, self.span, self.drop_share = settle, span, drop_share
        self.busy_share, self.min_side_px = busy_share, min_side_px
        # (received, dropped, busy_s, now_s) at the span's start
        self._mark: tuple[int, int, float, float] | None = None

    def update(self, received: int, dropped: int, busy_s: float, now_s: float,
               image_size: tuple[int, int] | None) -> DecimationStep | None:
        """The running counts (images received and dropped since the start), the time spent
        processing since the start and a monotonic clock (s), and the images' (width,
        height); a :class:`DecimationStep` when the decimation steps up, else None."""
        if self._mark is None:
            if received < self.settle:
                return None
            self._mark = (received, dropped, busy_s, now_s)
        n, d = received - self._mark[0], dropped - self._mark[1]
        if n < self.span:
            return None
        elapsed = now_s - self._mark[3]
        busy = (busy_s - self._mark[2]) / elapsed if elapsed > 0 else 0.0
        self._mark = (received, dropped, busy_s, now_s)
        nxt = self.factor + 1
        if (d <= self.drop_share * n and busy <= self.busy_share) or nxt > MAX_DECIMATION \
                or image_size is None or max(image_size) // nxt < self.min_side_px:
            return None
        step = DecimationStep(nxt, self.factor, n, d, busy)
        self.factor = nxt
        return step


@dataclass
class TrackerOptions:
    max_features: int = DEFAULT_MAX_FEATURES
    grid: tuple[int, int] = (8, 6)  # bucketing cells (columns, rows)
    quality_level: float = 0.01  # goodFeaturesToTrack, relative to the best corner
    min_distance_px: float = 8.0
    window_px: int = DEFAULT_WINDOW_PX  # the pyramid's KLT window (px), see above
    # then refine each track that passed the forward-backward check in the full-resolution
    # image with this smaller window, starting where the pyramid left it; a refinement that
    # moves the point by fb_threshold_px or more is not taken. 0: no refinement; None: the
    # pipeline's choice for its backend (REFINE_WINDOW_PX for the window backend, none for the
    # pairwise one), REFINE_WINDOW_PX for a tracker used alone
    refine_window_px: int | None = None
    pyramid_levels: int = 3
    fb_threshold_px: float = 1.0  # forward-backward consistency
    redetect_fraction: float = 0.8  # top up when fewer than this share of max_features remain
    # after a gap (an image more than GAP_RATIO of the last interval later: a frame the live
    # node dropped), start KLT both ways from each track's last image motion scaled to the
    # gap (new corners: the median of it) instead of from no motion: in a fast pan the
    # image moves past KLT's reach over two intervals (docs/notebook.md, "Tracking at camera
    # rate").
    # Needs the images' stamps (track(img, stamp_ns)). Not between consecutive frames: there
    # the last motion, which shake reverses every few frames, was a worse start than none
    # (A/B: 300-frame walks 1.5-4.5x worse ATE)
    predict_flow: bool = True
    # map the current image's grey levels into the previous one's (gain and offset fitted on
    # the tracked points) and track again when the brightness changed (auto exposure)
    photometric_compensation: bool = True
    # track at 1/decimation of the image's resolution (1: full resolution; MAX_DECIMATION):
    # the windows, distances and thresholds above are then in the reduced image's pixels.
    # For a live node that cannot keep up with large images (README, "Tracking at a reduced
    # resolution")
    decimation: int = 1
    # track again from the two images' global shift (phase correlation) when KLT keeps less
    # than RETRY_BELOW_SHARE of the tracks (a turn faster than KLT's reach)
    shift_retry: bool = True


@dataclass
class TrackedPair:
    """Correspondences of the previous and current frame (raw, distorted pixels) and ids."""

    pts_prev: np.ndarray  # (N, 2)
    pts_curr: np.ndarray  # (N, 2)
    ids: np.ndarray  # (N,) int track ids
    # (N,) each point's sensor row where the readout is not the image's rows top to bottom
    # (core/readout.py); None: the pixels' rows
    sensor_rows_prev: np.ndarray | None = None
    sensor_rows_curr: np.ndarray | None = None

    @property
    def rows_prev(self) -> np.ndarray:
        """(N,) the RS timing rows of ``pts_prev``."""
        return self.pts_prev[:, 1] if self.sensor_rows_prev is None else self.sensor_rows_prev

    @property
    def rows_curr(self) -> np.ndarray:
        return self.pts_curr[:, 1] if self.sensor_rows_curr is None else self.sensor_rows_curr


class FeatureTracker:
    """Tracks corners from frame to frame; call :meth:`track` with each new gray image."""

    def __init__(self, options: TrackerOptions | None = None):
        self.options = options or TrackerOptions()
        refine = self.options.refine_window_px
        check_refine_window(refine)
        check_window(self.options.window_px)
        check_decimation(self.options.decimation)
        self._refine_px = REFINE_WINDOW_PX if refine is None else int(refine)
        self._prev_img: np.ndarray | None = None
        self._prev_full: np.ndarray | None = None  # the last image at full resolution
        self._pts = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)
        self._next_id = 0
        self._flow = np.zeros((0, 2), np.float32)  # each feature's last image motion (px)
        self._flow_dt: float | None = None  # ... over this time (s)
        self._stamp_ns: int | None = None
        # (gain, offset) of the last image against the one before (``img ~ gain prev + offset``)
        # where it was tracked in the previous image's grey levels; None: no change found
        self.last_photometric: tuple[float, float] | None = None
        self._brightness_rate: tuple[float, float] | None = None  # the last significant change
        # the image shift (px, x and y, at the tracking resolution) the last image's tracks
        # were found from after KLT alone kept too few; None where KLT's own were taken
        self.last_shift: tuple[float, float] | None = None

    def reset(self) -> None:
        self._prev_img = self._prev_full = None
        self._pts = np.zeros((0, 2), np.float32)
        self._ids = np.zeros(0, np.int64)
        self._flow = np.zeros((0, 2), np.float32)
        self._flow_dt = self._stamp_ns = None
        self._brightness_rate = None
        self.last_shift = None

    @property
    def refine_window_px(self) -> int:
        """The refinement window in use (px; 0: no refinement)."""
        return self._refine_px

    @property
    def num_tracks(self) -> int:
        return len(self._pts)

    def current(self) -> tuple[np.ndarray, np.ndarray]:
        """Ids (n,) and raw pixels (n, 2) of every feature of the last image (tracked ones and
        the corners detected in it), in the full image's pixels."""
        return self._ids.copy(), to_full_resolution(self._pts.astype(float),
                                                    self.options.decimation)

    def track(self, img: np.ndarray, stamp_ns: int | None = None) -> TrackedPair:
        """Track the current features into ``img`` (uint8 gray), then top up by detection.
        ``stamp_ns``: the image's time, for the flow prediction (``predict_flow``; None: no
        prediction).

        Returns the correspondences that survived KLT and the forward-backward check (empty for
        the first frame or a changed image size), in ``img``'s pixels (also with
        ``decimation``).
        """
        factor = self.options.decimation
        pair = self._track(decimated(img, factor), stamp_ns)
        self._prev_full = img
        if factor > 1:
            pair.pts_prev = to_full_resolution(pair.pts_prev, factor)
            pair.pts_curr = to_full_resolution(pair.pts_curr, factor)
        return pair

    def set_decimation(self, factor: int) -> None:
        """Track the next images at ``factor`` (:attr:`TrackerOptions.decimation`) without
        losing a track: the features, their last image motion and the previous image (averaged
        down again from the full-resolution one) are carried over to the new resolution."""
        check_decimation(factor)
        old = self.options.decimation
        if factor == old:
            return
        self.options.decimation = factor
        if self._prev_full is None:
            return
        self._prev_img = decimated(self._prev_full, factor)
        full = to_full_resolution(self._pts.astype(float), old)
        self._pts = ((full + 0.5) / factor - 0.5).astype(np.float32)
        self._flow = (self._flow * np.float32(old / factor)).astype(np.float32)

    def _track(self, img: np.ndarray, stamp_ns: int | None) -> TrackedPair:
        """:meth:`track` in the tracking resolution's pixels."""
        o = self.options
        empty = TrackedPair(np.zeros((0, 2)), np.zeros((0, 2)), np.zeros(0, np.int64))
        self.last_photometric = None
        turning = self.last_shift is not None  # the last image came from a shift
        self.last_shift = None
        dt = None
        if stamp_ns is not None and self._stamp_ns is not None:
            dt = (stamp_ns - self._stamp_ns) * 1e-9
        self._stamp_ns = stamp_ns
        if self._prev_img is None or self._prev_img.shape != img.shape or not len(self._pts):
            pair = empty
            self._pts = np.zeros((0, 2), np.float32)
            self._ids = np.zeros(0, np.int64)
            self._flow, self._flow_dt = np.zeros((0, 2), np.float32), None
            self._brightness_rate = None
        else:
            guess = self._predicted_motion(dt)
            rate = self._brightness_rate
            shift = None
            first = False  # tracked from the shift first (a turn's next frame)
            if o.shift_retry and turning and guess is None:
                shift = global_shift(self._prev_img, img)
                first = self._far(shift, SHIFT_FIRST_WINDOWS) and self._klt_alone_fails(img)
                if first:
                    p1f, good = self._shift_first(img, shift, rate)
            if not first:
                p1f, good = self._track_photometric(img, guess)
                if o.shift_retry and good.sum() < RETRY_BELOW_SHARE * len(good):
                    p1f, good = self._retry_from_shift(img, p1f, good, rate, shift)
            pair = TrackedPair(self._pts[good].astype(float), p1f[good].astype(float),
                               self._ids[good].copy())  # fmt: skip
            self._flow = (p1f[good] - self._pts[good]).astype(np.float32)
            self._flow_dt = dt
            self._pts = p1f[good].astype(np.float32)
            self._ids = self._ids[good]
        n_tracked = len(self._pts)
        if n_tracked < o.redetect_fraction * o.max_features:
            self._detect(img)
        # new corners move as the median track did
        fill = np.median(self._flow, axis=0) if n_tracked else np.zeros(2, np.float32)
        self._flow = np.vstack([self._flow[:n_tracked],
                                np.tile(fill, (len(self._pts) - n_tracked, 1))]).astype(np.float32)
        self._prev_img = img
        return pair

    def _klt(self, prev: np.ndarray, img: np.ndarray, guess: np.ndarray | None,
             subset: np.ndarray | None = None) -> tuple[np.ndarray, np.ndarray]:
        """Pyramidal KLT of the features from ``prev`` into ``img`` with the forward-backward
        check and the full-resolution refinement: (n, 2) positions and (n,) which are good.
        ``subset``: only these features' indices, without the refinement (which moves a kept
        track but does not decide whether it is kept)."""
        o = self.options
        lk = dict(winSize=(o.window_px, o.window_px), maxLevel=o.pyramid_levels,
                  criteria=(cv2.TERM_CRITERIA_EPS | cv2.TERM_CRITERIA_COUNT, 30, 0.01))
        p0 = (self._pts if subset is None else self._pts[subset]).reshape(-1, 1, 2)
        # after a gap, both ways from the prediction: back from where the point landed,
        # started where the predicted motion takes it back to
        if guess is not None:
            lk["flags"] = cv2.OPTFLOW_USE_INITIAL_FLOW
        p1, st1, _ = cv2.calcOpticalFlowPyrLK(prev, img, p0,
                                              None if guess is None else p0 + guess, **lk)
        p0b, st2, _ = cv2.calcOpticalFlowPyrLK(img, prev, p1,
                                               None if guess is None else p1 - guess, **lk)
        fb = np.linalg.norm((p0b - p0).reshape(-1, 2), axis=1)
        h, w = img.shape
        p1f = p1.reshape(-1, 2)
        good = (st1.ravel() == 1) & (st2.ravel() == 1) & (fb < o.fb_threshold_px)
        good &= np.isfinite(p1f).all(axis=1)
        good &= (p1f[:, 0] >= 0) & (p1f[:, 0] <= w - 1) & (p1f[:, 1] >= 0)
        good &= p1f[:, 1] <= h - 1
        if self._refine_px and good.any() and subset is None:
            p1r, st3, _ = cv2.calcOpticalFlowPyrLK(
                prev, img, p0[good], p1[good],
                winSize=(self._refine_px,) * 2, maxLevel=0, criteria=lk["criteria"],
                flags=cv2.OPTFLOW_USE_INITIAL_FLOW)
            p1r = p1r.reshape(-1, 2)
            ok = (st3.ravel() == 1) & np.isfinite(p1r).all(axis=1)
            ok &= np.linalg.norm(p1r - p1f[good], axis=1) < o.fb_threshold_px
            p1f[np.flatnonzero(good)[ok]] = p1r[ok]
        return p1f, good

    def _track_photometric(self, img: np.ndarray,
                           guess: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        """KLT into ``img`` (:meth:`_klt`); with ``photometric_compensation``, into ``img`` in
        the previous image's grey levels where its brightness changed: first mapped by the last
        image's change (an auto exposure ramps over several frames), then, while the tracked
        points show a change beyond the tolerance, by the refitted one (tracks found under a
        changed brightness are a little off, and so is a first fit), at most
        ``PHOTOMETRIC_ROUNDS`` more times."""
        if not self.options.photometric_compensation:
            return self._klt(self._prev_img, img, guess)
        prev_levels = _patch_levels(self._prev_img, self._pts)
        applied = self._brightness_rate
        mapped = _map_levels(img, applied)
        p1, good = self._klt(self._prev_img, mapped, guess)
        for k in range(PHOTOMETRIC_ROUNDS + 1):
            fit = self._photometric_change(prev_levels, mapped, p1, good)
            total = _compose(applied, None if fit is None else fit[:2])
            self._brightness_rate = total if fit is not None and _changed(total, fit[3]) \
                else None  # fmt: skip
            if fit is None or not fit[2] or k == PHOTOMETRIC_ROUNDS:
                break
            applied = total
            mapped = _map_levels(img, applied)
            p1, good = self._klt(self._prev_img, mapped, guess)
        self.last_photometric = applied
        return p1, good

    def _photometric_change(self, prev_levels: tuple[np.ndarray, np.ndarray], img: np.ndarray,
                            p1: np.ndarray,
                            good: np.ndarray) -> tuple[float, float, bool, np.ndarray] | None:
        """``(gain, offset, changed, levels)``: ``img ~ gain * prev + offset``, whether that
        changes a grey level by more than ``PHOTOMETRIC_TOLERANCE`` between ``levels``, the
        5th and 95th percentile of the previous image's fitted grey levels; None without a
        fit. Fitted on the mean grey levels around the tracked points (``prev_levels``:
        :func:`_patch_levels` of the previous image at the features; not where either patch is
        clipped) with one round of outlier rejection; with fewer than
        ``PHOTOMETRIC_MIN_POINTS`` such tracks, on the images' own percentiles."""
        x = y = np.zeros(0)
        if good.sum() >= PHOTOMETRIC_MIN_POINTS:
            y, y_clipped = _patch_levels(img, p1[good])
            keep = ~prev_levels[1][good] & ~y_clipped
            x, y = prev_levels[0][good][keep], y[keep]
        if len(x) < PHOTOMETRIC_MIN_POINTS:  # the images' grey-level distributions instead
            q = np.linspace(5.0, 95.0, 19)
            x = np.percentile(self._prev_img[::4, ::4], q)
            y = np.percentile(img[::4, ::4], q)
            lo, hi = PHOTOMETRIC_CLIPPED
            keep = (x > lo) & (x < hi) & (y > lo) & (y < hi)
            x, y = x[keep], y[keep]
        fit = _line_fit(x, y)
        if fit is None:
            return None
        levels = np.percentile(x, [5.0, 95.0])
        return fit[0], fit[1], _changed(fit, levels), levels

    def _far(self, shift: tuple[float, float] | None, windows: float = 0.5) -> bool:
        """Whether a measured image shift is at least ``windows`` KLT windows (half a window:
        worth tracking from)."""
        return shift is not None and np.hypot(*shift) >= windows * self.options.window_px

    def _retry_from_shift(self, img: np.ndarray, p1f: np.ndarray, good: np.ndarray,
                          rate: tuple[float, float] | None,
                          shift: tuple[float, float] | None = None,
                          ) -> tuple[np.ndarray, np.ndarray]:  # fmt: skip
        """KLT kept too few tracks into ``img``: track every feature again from the global
        shift between the previous image and ``img`` (:func:`global_shift`, or ``shift``
        where it is already measured) if it is at least half the KLT window, with the
        brightness change ``rate`` the first attempt started from; the attempt that keeps
        more tracks, and :attr:`last_shift` where it is the new one."""
        if shift is None:
            shift = global_shift(self._prev_img, img)
        if not self._far(shift):
            return p1f, good
        first = (p1f, good, self._brightness_rate, self.last_photometric)
        self._brightness_rate = rate
        guess = np.tile(np.float32(shift), (len(self._pts), 1)).reshape(-1, 1, 2)
        p1s, goods = self._track_photometric(img, guess)
        if goods.sum() <= good.sum():
            _, _, self._brightness_rate, self.last_photometric = first
            return p1f, good
        self.last_shift = shift
        return p1s, goods

    def _klt_alone_fails(self, img: np.ndarray) -> bool:
        """Whether KLT from no motion keeps under ``PROBE_FAILS_BELOW`` of ``PROBE_FEATURES``
        features spread over the list (evenly spaced indices; the features were detected cell
        by cell over the image), tried into ``img`` as the first attempt's first pass is (in
        the last image's brightness change where ``photometric_compensation`` is on); False
        with too few features to tell."""
        n = len(self._pts)
        if n < 2 * PROBE_FEATURES:
            return False
        subset = np.linspace(0, n - 1, PROBE_FEATURES).round().astype(np.int64)
        mapped = _map_levels(img, self._brightness_rate) \
            if self.options.photometric_compensation else img  # fmt: skip
        _, good = self._klt(self._prev_img, mapped, None, subset)
        return good.mean() < PROBE_FAILS_BELOW

    def _shift_first(self, img: np.ndarray, shift: tuple[float, float],
                     rate: tuple[float, float] | None) -> tuple[np.ndarray, np.ndarray]:
        """The attempts of a turn's frame in the other order, where KLT from no motion is
        known to fail (:meth:`_klt_alone_fails`): every feature is tracked from ``shift``
        first; where that keeps at least ``RETRY_BELOW_SHARE`` of the tracks it is taken (as
        :meth:`_retry_from_shift` would take it after the failed pass), else KLT from no
        motion is tried too, with the same brightness change ``rate``, and the attempt that
        keeps more tracks is taken (KLT's own on a tie, as :meth:`_retry_from_shift`)."""
        guess = np.tile(np.float32(shift), (len(self._pts), 1)).reshape(-1, 1, 2)
        p1s, goods = self._track_photometric(img, guess)
        if goods.sum() >= RETRY_BELOW_SHARE * len(goods):
            self.last_shift = shift
            return p1s, goods
        shifted = (self._brightness_rate, self.last_photometric)
        self._brightness_rate = rate
        p1f, good = self._track_photometric(img, None)
        if goods.sum() <= good.sum():
            return p1f, good
        self._brightness_rate, self.last_photometric = shifted
        self.last_shift = shift
        return p1s, goods

    def _predicted_motion(self, dt: float | None) -> np.ndarray | None:
        """(n, 1, 2) image motion of each feature expected by ``dt`` s after the last image
        (its last motion at the same rate) after a gap, None without one or without a
        prediction."""
        if not self.options.predict_flow or dt is None or not self._flow_dt \
                or self._flow_dt <= 0 or len(self._flow) != len(self._pts):  # fmt: skip
            return None
        ratio = dt / self._flow_dt
        if not GAP_RATIO < ratio <= MAX_PREDICTION_RATIO:
            return None
        return (self._flow * np.float32(ratio)).reshape(-1, 1, 2)

    def _detect(self, img: np.ndarray) -> None:
        """Add corners in grid cells with fewer than their share of tracks."""
        o = self.options
        h, w = img.shape
        cols, rows = o.grid
        per_cell = max(1, int(np.ceil(o.max_features / (cols * rows))))
        mask = np.full((h, w), 255, np.uint8)
        for x, y in self._pts:
            cv2.circle(mask, (int(x), int(y)), int(o.min_distance_px), 0, -1)
        cx = np.clip((self._pts[:, 0] * cols / w).astype(int), 0, cols - 1)
        cy = np.clip((self._pts[:, 1] * rows / h).astype(int), 0, rows - 1)
        counts = np.zeros((rows, cols), int)
        np.add.at(counts, (cy, cx), 1)
        new = []
        budget = o.max_features - len(self._pts)
        for r in range(rows):
            for c in range(cols):
                need = min(per_cell - counts[r, c], budget - sum(len(n) for n in new))
                if need <= 0:
                    continue
                x0, x1 = c * w // cols, (c + 1) * w // cols
                y0, y1 = r * h // rows, (r + 1) * h // rows
                corners = cv2.goodFeaturesToTrack(img[y0:y1, x0:x1], need, o.quality_level,
                                                  o.min_distance_px, mask=mask[y0:y1, x0:x1])
                if corners is not None:
                    new.append(corners.reshape(-1, 2) + [x0, y0])
        if new:
            pts = np.concatenate(new).astype(np.float32)
            self._pts = np.concatenate([self._pts, pts])
            self._ids = np.concatenate([self._ids,
                                        np.arange(self._next_id, self._next_id + len(pts))])
            self._next_id += len(pts)


def global_shift(prev: np.ndarray, img: np.ndarray,
                 side_px: int = GLOBAL_SHIFT_SIDE_PX) -> tuple[float, float] | None:
    """The shift (px, x and y) that moves ``prev``'s content onto ``img``'s (two gray images of
    one size), by phase correlation (``cv2.phaseCorrelate``, Hann window) on copies averaged
    down by an integer factor to about ``side_px`` on their longer side; None where the images
    are too small to measure it or it is not finite."""
    factor = max(1, int(round(max(prev.shape[:2]) / side_px)))
    a, b = decimated(prev, factor), decimated(img, factor)
    if min(a.shape[:2]) < 8:
        return None
    window = cv2.createHanningWindow((a.shape[1], a.shape[0]), cv2.CV_32F)
    (dx, dy), _ = cv2.phaseCorrelate(a.astype(np.float32), b.astype(np.float32), window)
    if not np.isfinite([dx, dy]).all():
        return None
    return float(dx * factor), float(dy * factor)


def _map_levels(img: np.ndarray, change: tuple[float, float] | None) -> np.ndarray:
    """``img`` in the grey levels of an image it is ``change = (gain, offset)`` of
    (``img ~ gain * other + offset``); ``img`` itself for None."""
    if change is None:
        return img
    levels = (np.arange(256) - change[1]) / change[0]
    return cv2.LUT(img, np.clip(np.round(levels), 0, 255).astype(np.uint8))


def _compose(first: tuple[float, float] | None,
             then: tuple[float, float] | None) -> tuple[float, float] | None:
    """The change of ``img`` where ``img ~ first(mapped)`` and ``mapped ~ then(prev)``."""
    if first is None or then is None:
        return then if first is None else first
    return first[0] * then[0], first[0] * then[1] + first[1]


def _changed(change: tuple[float, float], levels: np.ndarray) -> bool:
    """Whether ``change`` moves a grey level between ``levels`` by more than the tolerance."""
    return bool(np.max(np.abs((change[0] - 1.0) * levels + change[1])) > PHOTOMETRIC_TOLERANCE)


def _patch_levels(img: np.ndarray, pts: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Mean grey level (n,) of the ``PHOTOMETRIC_PATCH`` x ``PHOTOMETRIC_PATCH`` pixels
    around each of ``pts`` (n, 2) (x, y; rounded, kept inside the image), and whether the
    patch has a clipped pixel (n,)."""
    h, w = img.shape
    r = PHOTOMETRIC_PATCH // 2
    d = np.arange(-r, r + 1)
    x = np.clip(np.round(pts[:, 0]).astype(int), r, w - 1 - r)
    y = np.clip(np.round(pts[:, 1]).astype(int), r, h - 1 - r)
    patch = img[(y[:, None] + d)[:, :, None], (x[:, None] + d)[:, None, :]]
    lo, hi = PHOTOMETRIC_CLIPPED
    flat = patch.reshape(len(pts), -1)
    return flat.mean(axis=1), (flat.min(axis=1) <= lo) | (flat.max(axis=1) >= hi)


def _line_fit(x: np.ndarray, y: np.ndarray) -> tuple[float, float] | None:
    """``y ~ gain * x + offset`` by least squares, refitted without the points beyond 3 robust
    sigmas; None where ``x`` has no spread or the gain is not positive."""
    keep = np.ones(len(x), bool)
    for _ in range(2):
        if keep.sum() < 3 or np.ptp(x[keep]) < 1.0:
            return None
        xk, yk = x[keep], y[keep]
        gain = float(np.mean((xk - xk.mean()) * (yk - yk.mean())) / np.var(xk))
        offset = float(yk.mean() - gain * xk.mean())
        r = y - (gain * x + offset)
        sigma = 1.4826 * np.median(np.abs(r[keep])) + 1e-6
        keep = np.abs(r) <= 3.0 * sigma
    if not (np.isfinite(gain) and np.isfinite(offset)) or gain <= 0.05:
        return None
    return float(gain), float(offset)
