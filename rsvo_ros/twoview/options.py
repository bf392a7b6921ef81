"""Settings of the two-view estimator, RANSAC kept apart from the optimizer (PoseLib style)."""

from __future__ import annotations

from dataclasses import dataclass

PAPER_RANSAC_ITERATIONS = 500  # Algorithm 1
PAPER_SAMPLE_SIZE = 20  # Sec. 6: "20 feature point correspondences as the input of RANSAC"


@dataclass
class RansacOptions:
    """Robust-estimation settings, kept apart from the optimizer's (PoseLib style)."""

    threshold_px: float = 1.0  # Sampson distance of an inlier, pixels
    max_iterations: int = 1000  # hypotheses of the GS baselines (OpenCV, MVO)
    confidence: float = 0.999
    rs_iterations: int = PAPER_RANSAC_ITERATIONS  # paper mode: LM runs on random 20-point samples
    rs_sample_size: int = PAPER_SAMPLE_SIZE
    init_threshold_px: float = 3.0  # GS initialisation of the RS model tolerates RS distortion
    init_max_iterations: int = 50  # USAC stops early by its confidence; this caps the worst case
    # the best GS fit (USAC_MAGSAC at threshold_px) the RS model starts from and is weighed
    # against: MAGSAC++ stops early by its confidence on real data (80-100 % inliers); where
    # the RS distortion leaves 40 %, 1000 iterations took 15 ms and 100 took 5
    null_max_iterations: int = 100


@dataclass
class LMOptions:
    """Levenberg-Marquardt and search settings of the RS model (RANSAC options are separate).

    The velocity prior and bounds are in image-independent units: rotation (rad) and
    displacement (baselines, ``|t| = 1``) over half the readout, i.e. over the largest row time
    ``s_max`` of the points from the reference row.
    """

    max_iterations: int = 30  # final refinements
    sample_iterations: int = 8  # per RANSAC hypothesis (paper mode: Algorithm 1's LM)
    lambda_init: float = 1e-3
    rel_tol: float = 1e-7  # stop when a hypothesis improves by less than this fraction
    # ... in the refinements on all points that choose the candidate the polish (rel_tol)
    # finishes: 1e-7 took 18 iterations per candidate on the bench's pairs, 1e-4 about half,
    # with the same errors (docs/notebook.md, "The estimator's speed")
    refine_rel_tol: float = 1e-4
    robust_scale_px: float = 2.0  # Cauchy loss scale of the all-points refinement
    max_angular_velocity: float = 5.0  # rad/s (286 deg/s): bound of the search
    max_readout_translation: float = 5.0  # baselines over half the readout: bound
    prior_rotation_rad: float = 0.3  # prior std of the rotation over half the readout
    prior_translation: float = 20.0  # prior std of the displacement over half the readout
    max_rotation_change_rad: float = 0.1  # how far (5.7 deg) a run may rotate from its start
    init_thresholds_px: tuple[float, ...] = (8.0,)  # extra GS starts (fast mode; the 1 px one
    # is the best GS fit, USAC_MAGSAC)
    samples_per_start: int = 6  # fast mode: LM runs on random samples from each GS start
    sample_size: int = 40  # fast mode: correspondences per sample
    sample_difference_iterations: int = 4  # fast mode: first with only velocity differences
    sample_full_iterations: int = 4  # fast mode: then all 17 DOF
    final_candidates: int = 2  # fast mode: distinct best sample runs refined on all points
    # fast mode: where the best GS fit explains the data within this robust scale (px; smooth
    # real video), the RS fit is refined locally from it instead of searched from many starts
    local_scale_px: float = 1.0
    polish_rounds: int = 1  # final refinements on the inliers with the noise-scaled prior
    # With the frames' interval known (a video stream), the prior is centred on the constant
    # velocity of the pair's own motion instead of zero (the paper's source mentions, commented
    # out, taking the velocities from the nearest frames), with these scales of the departure
    # from it over half the readout, in the units of prior_* (at a 1000 px focal length): the
    # translation 130x tighter (on 16 synthetic vehicle sequences at 500 px a translation scale
    # of 0.05 to 0.15 did best, 0.5 clearly worse; a rotation scale of 0.015 worse, 0.05 to 0.5
    # alike). 0: keep the zero-mean prior.
    motion_prior_rotation_rad: float = 0.15
    motion_prior_translation: float = 0.15
    # "held_out": the RS fit must predict held-out points better than the model without free
    # velocities (GS for a lone pair, the pair's own constant velocity for a stream); "aic":
    # Akaike with the RS fit's noise level against a GS fit; "off"
    model_selection: str = "held_out"
