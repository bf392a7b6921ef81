"""The line-delay refinement of a live pipeline in a process of its own at the lowest CPU
priority (``PipelineOptions.line_delay_auto_refine_frames`` with async mapping: the node).

The pipeline writes the kept frames, its options and its line-delay calibrator's windows to a
file (:class:`RefineJob`), a ``nice -n 19`` Python (in the idle scheduling class too once it
runs: :func:`lower_thread_priority`) runs
:func:`~rsvo_ros.odometry.pipeline.refine_from_estimate` on them (an estimate over all the
windows, then the second pass; ``python -m rsvo_ros.odometry.refine_worker IN OUT``) and
writes its results; the pipeline polls the process at each frame. Before the second pass it
writes the estimate it starts from (:meth:`RefineJob.started_from`), which the pipeline uses
while the pass runs. A process, not a thread: on a thread the second pass held the GIL
against the tracking and cost half the frames at 1280x720, 15 Hz (README, "Refining the
estimate"); niced from its start, so that its imports take only what the tracking leaves too.
"""

from __future__ import annotations

import dataclasses
import os
import pickle
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

from rsvo_ros.odometry.line_delay import LineDelayEstimate, RefinedLineDelay

LOWEST_PRIORITY = 19  # nice value of the background work (the refinement, the calibrator)
# beside the results: the estimate the second pass starts from, written before the pass
START_FILE = "start.pickle"


def lower_thread_priority(niceness: int = LOWEST_PRIORITY) -> bool:
    """Run the calling thread as background work: Linux's idle scheduling class
    (``SCHED_IDLE``: it runs only on a core nothing else wants, and gives the core up at
    once when another thread wakes) and ``niceness``. Linux schedules threads one by one:
    the process's other threads keep theirs; threads started later by this one inherit it.
    For work that must not take the CPU from the tracking: the line-delay refinement's
    process and the calibrator's estimates on their thread. It does not make the work free:
    on a 2-core VM an idle-class busy loop still cost the node 3-6 % of its frames (README,
    "The calibrator's re-solves, warm-started"). False where the system has neither (then
    the thread runs as before)."""
    done = False
    try:
        tid = threading.get_native_id()
        os.setpriority(os.PRIO_PROCESS, tid, max(os.getpriority(os.PRIO_PROCESS, tid),
                                                 niceness))  # fmt: skip
        done = True
        os.sched_setscheduler(tid, os.SCHED_IDLE, os.sched_param(0))
    except (AttributeError, OSError):
        pass
    return done


class RefineJob:
    """One refinement in the background: ``args`` for ``refine_from_estimate``; :meth:`done`
    polls, :meth:`result` reads the outcome (status "failed" with the reason when the process
    did not give one), :meth:`cancel` stops it. The inputs are written on a thread (large writes
    release the GIL), then the process starts."""

    def __init__(self, args: tuple):
        self._dir = Path(tempfile.mkdtemp(prefix="rsvo_refine_"))
        self._in, self._out = self._dir / "in.pickle", self._dir / "out.pickle"
        self._start_file = self._dir / START_FILE
        self._started_from: LineDelayEstimate | None = None
        self._proc: subprocess.Popen | None = None
        self._error: str | None = None
        self._cancelled = False
        self._lock = threading.Lock()
        self._starter = threading.Thread(target=self._start, args=(args,),
                                         name="rsvo_line_delay_refine", daemon=True)  # fmt: skip
        self._starter.start()

    def _start(self, args: tuple) -> None:
        try:
            with open(self._in, "wb") as f:
                pickle.dump(args, f, protocol=5)
            nice = shutil.which("nice")
            cmd = [sys.executable, "-m", "rsvo_ros.odometry.refine_worker", str(self._in),
                   str(self._out)]  # fmt: skip
            with self._lock:
                if self._cancelled:
                    return
                self._proc = subprocess.Popen(([nice, "-n", str(LOWEST_PRIORITY)] if nice
                                               else []) + cmd,
                                              stdout=subprocess.DEVNULL,
                                              stderr=subprocess.PIPE)  # fmt: skip
        except (OSError, pickle.PicklingError) as exc:
            self._error = f"could not start the second pass: {exc!r}"

    def done(self) -> bool:
        if self._starter.is_alive():
            return False
        return self._proc is None or self._proc.poll() is not None

    def started_from(self) -> LineDelayEstimate | None:
        """The estimate the second pass started from (the calibrator's over all its windows),
        once the process has handed it over, before the pass ends; None before (or if the
        process gives none)."""
        if self._started_from is None and self._start_file.exists():
            try:
                with open(self._start_file, "rb") as f:
                    self._started_from = LineDelayEstimate(**pickle.load(f))
            except (OSError, EOFError, pickle.UnpicklingError, TypeError):
                return None  # removed by a cancel meanwhile, or not the worker's
        return self._started_from

    def wait(self, timeout: float) -> None:
        """Until done, at most about ``timeout`` seconds."""
        self._starter.join(timeout)
        if self._proc is not None:
            try:
                self._proc.wait(timeout=max(timeout, 0.0))
            except subprocess.TimeoutExpired:
                pass

    def result(self) -> tuple[LineDelayEstimate | None, RefinedLineDelay]:
        """The outcome once :meth:`done`: the estimate refined (None when the process gave
        none) and the refinement (status "failed" with the reason when the process did not
        finish it). The files are removed then."""
        try:
            if self._error is not None:
                return None, RefinedLineDelay("failed", reason=self._error)
            if self._proc is None or self._proc.poll() is None:
                return None, RefinedLineDelay("failed", reason="the second pass did not finish")
            if self._proc.returncode != 0 or not self._out.exists():
                err = (self._proc.stderr.read() or b"").decode(errors="replace").strip()
                last = err.splitlines()[-1] if err else "no message"
                return None, RefinedLineDelay(
                    "failed", reason=f"the second pass's process exited with "
                                     f"{self._proc.returncode}: {last}")  # fmt: skip
            with open(self._out, "rb") as f:
                start, ref = pickle.load(f)
            return LineDelayEstimate(**start), RefinedLineDelay(**ref)
        finally:
            self.cancel()

    def cancel(self) -> None:
        """Stop the process (if running) and remove the files."""
        with self._lock:
            self._cancelled = True
            if self._proc is not None and self._proc.poll() is None:
                self._proc.kill()
                self._proc.wait()
            if self._proc is not None and self._proc.stderr is not None:
                self._proc.stderr.close()
        shutil.rmtree(self._dir, ignore_errors=True)


def main(argv: list[str] | None = None) -> int:
    """``python -m rsvo_ros.odometry.refine_worker IN OUT``:
    ``refine_from_estimate(*pickle(IN))``, its results' fields pickled to OUT."""
    lower_thread_priority()  # the process started niced; idle too, before the imports
    from rsvo_ros.odometry.pipeline import refine_from_estimate

    src, dst = (argv if argv is not None else sys.argv[1:])[:2]
    with open(src, "rb") as f:
        args = pickle.load(f)

    def hand_over(start: LineDelayEstimate) -> None:  # read by RefineJob.started_from
        _write(Path(dst).with_name(START_FILE), dataclasses.asdict(start))

    start, ref = refine_from_estimate(*args, on_start=hand_over)
    _write(Path(dst), (dataclasses.asdict(start), ref.as_dict()))
    return 0


def _write(path: Path, obj) -> None:
    """Pickle ``obj`` to ``path`` whole or not at all (a reader never sees half a file)."""
    tmp = path.with_suffix(".tmp")
    with open(tmp, "wb") as f:
        pickle.dump(obj, f)
    tmp.replace(path)


if __name__ == "__main__":
    sys.exit(main())
