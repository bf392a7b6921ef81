"""The paper (Lee & Yoon, Secs. 5-6): two-view relative pose with the 17-DOF rolling-shutter
essential matrix, and the GS (OpenCV 5-point) and MVO (8-point) baselines.

Modules, top to bottom (each uses only the ones below it):

- :mod:`~rsvo_ros.twoview.estimator`: :func:`estimate_relative_pose` (input checks, the GS/MVO
  baselines, the result object);
- :mod:`~rsvo_ros.twoview.search`: starts, sampling, velocity prior, model selection;
- :mod:`~rsvo_ros.twoview.essential`: GS two-view geometry (the baselines and the starts);
- :mod:`~rsvo_ros.twoview.solver` over :mod:`~rsvo_ros.twoview.kernels`: the compiled model
  (residuals, Jacobians, Levenberg-Marquardt, depths);
- :mod:`~rsvo_ros.twoview.state` and :mod:`~rsvo_ros.twoview.options`: data and settings.

:mod:`~rsvo_ros.twoview.reference` is the readable numpy specification of the model that the
tests check the kernels against; nothing at run time uses it.
"""

from rsvo_ros.twoview.estimator import RelativePoseResult, estimate_relative_pose, warm_up
from rsvo_ros.twoview.options import LMOptions, RansacOptions

__all__ = ["LMOptions", "RansacOptions", "RelativePoseResult", "estimate_relative_pose",
           "warm_up"]
