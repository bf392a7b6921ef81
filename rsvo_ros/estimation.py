"""The stable import path of the two-view API (CONTRACTS.md): a re-export of
:mod:`rsvo_ros.twoview`, where the estimator lives."""

from rsvo_ros.twoview.estimator import (
    MODELS,
    RS_MODES,
    RelativePoseResult,
    estimate_relative_pose,
    warm_up,
)
from rsvo_ros.twoview.options import LMOptions, RansacOptions

__all__ = ["MODELS", "RS_MODES", "LMOptions", "RansacOptions", "RelativePoseResult",
           "estimate_relative_pose", "warm_up"]
