"""Command-line tools over the pipeline and the estimator: ``rsvo_replay``, ``rsvo_bench``,
``rsvo_synth`` and the trajectory comparison. They may use :mod:`rsvo_ros.ros`'s bag I/O."""

from rsvo_ros import limit_blas_threads

limit_blas_threads()  # before numpy loads OpenBLAS
