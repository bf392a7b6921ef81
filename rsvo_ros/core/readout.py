"""Which way a rolling shutter reads the image out, as the image arrives.

CONTRACTS.md: an image's rows are exposed top to bottom from its stamp (row ``r`` at ``stamp +
r * line_delay``). A camera mounted upside down whose driver turns the image the right way up
(``rotate 180``) delivers images whose *bottom* row was read first; a phone filming in portrait,
or a camera on its side whose image is turned by 90 degrees, reads them column by column. The
RS model only needs each pixel's time, so such images keep their geometry and get a "sensor row"
instead of their row: the number of lines read before the pixel's line. ``line_delay`` is then
the time per sensor line (an image column for ``right`` / ``left``), and the stamp the time of
the first line read.

- ``down``: rows top to bottom (the contract's, the default): sensor row = ``y``;
- ``up``: rows bottom to top (an image turned by 180 degrees): ``height - 1 - y``;
- ``right``: columns left to right (turned by 90 degrees one way): ``x``;
- ``left``: columns right to left (the other way): ``width - 1 - x``.
"""

from __future__ import annotations

import numpy as np

READOUTS = ("down", "up", "right", "left")


def check_readout(readout: str) -> str:
    if readout not in READOUTS:
        raise ValueError(f"readout must be one of {READOUTS}, got {readout!r}")
    return readout


def sensor_rows(px: np.ndarray, readout: str, width: int, height: int) -> np.ndarray:
    """(N,) sensor rows (lines read before each pixel's) of raw image pixels ``px`` (N, 2)."""
    px = np.asarray(px, float)
    if readout == "down":
        return px[:, 1]
    if readout == "up":
        return (height - 1.0) - px[:, 1]
    if readout == "right":
        return px[:, 0]
    if readout == "left":
        return (width - 1.0) - px[:, 0]
    raise ValueError(f"readout must be one of {READOUTS}, got {readout!r}")


def sensor_line_count(readout: str, width: int, height: int) -> int:
    """Lines read per image: its rows, or its columns for ``right`` / ``left``."""
    return int(width if check_readout(readout) in ("right", "left") else height)
