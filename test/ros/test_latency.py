"""The latency probe's bookkeeping (the probe itself runs against a live node: README)."""

from __future__ import annotations

from rsvo_ros.ros.latency import _frame_counts


def test_frame_counts_come_from_the_nodes_diagnostics():
    diag = {"received": "90", "processed": "85", "dropped": "5", "held": "0",
            "tracking_state": "tracking", "line_delay": "5e-05"}
    assert _frame_counts(diag) == {"received": 90, "processed": 85, "dropped": 5, "held": 0}
    assert _frame_counts({}) == {}  # no diagnostics yet
