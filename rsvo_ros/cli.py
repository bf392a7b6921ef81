"""Console-script entry points that are not implemented yet.

Each exits with status 2 and says so, until the issue that builds it lands; none of them claims
to do more than that.
"""

from __future__ import annotations

import sys

NOT_IMPLEMENTED_EXIT = 2


def _not_implemented(name: str, what: str) -> int:
    print(
        f"{name}: not implemented yet ({what}); see README.md for what works today.",
        file=sys.stderr,
    )
    return NOT_IMPLEMENTED_EXIT


def node_main(argv: list[str] | None = None) -> int:
    """Entry point of ``rsvo_node`` (the live ROS 2 node)."""
    if argv is None and any(a in ("-h", "--help") for a in sys.argv[1:]):
        print("usage: rsvo_node [--ros-args ...]  (not implemented yet)")
        return 0
    sys.exit(_not_implemented("rsvo_node", "the live node arrives with the node issue"))


def play_main(argv: list[str] | None = None) -> int:
    """Entry point of ``rsvo_play`` (publishes a bag's topics live)."""
    sys.exit(_not_implemented("rsvo_play", "bag playback arrives with the node issue"))
