"""Points a scan holds more than once (the same x, y, z), found in one compiled pass.

A repeated point adds nothing to the surface, and it fills its own neighbourhood: the network's
neighbour sets, curvature and local frames of that patch then see one point several times, and
the copies it makes stack on their parent (`cadpu.inference.Upsampler.upsample_object` collapses
them for the same reason). KITTI's scans hold none; merged clouds, dual-return sensors and
re-exported scans may.
"""

from __future__ import annotations

import numpy as np
from numba import njit


def repeated_rows(xyz: np.ndarray) -> np.ndarray:
    """Which rows repeat an earlier row's x, y, z exactly.

    Args:
        xyz: (N, 3) coordinates (compared as float32, as scans store them; 0.0 and -0.0 equal).

    Returns:
        (N,) bool, True for every row whose x, y, z equal those of a row before it (the first of
        each set of equal rows is False).
    """
    coordinates = np.ascontiguousarray(xyz, dtype=np.float32) + np.float32(0.0)  # -0.0 becomes 0.0
    if coordinates.ndim != 2 or coordinates.shape[1] != 3:
        raise ValueError(f"repeated_rows: xyz must be (N, 3), got shape {coordinates.shape}")
    return _repeated_rows(coordinates.view(np.uint32))


@njit(cache=True, nogil=True)
def _repeated_rows(bits: np.ndarray) -> np.ndarray:  # pragma: no cover - compiled
    # Open addressing over a table of at least twice the rows; a slot holds row + 1 (0: empty).
    n = bits.shape[0]
    size = 1
    while size < 2 * n:
        size *= 2
    table = np.zeros(size, np.int32)
    repeated = np.zeros(n, np.bool_)
    for row in range(n):
        x, y, z = np.uint64(bits[row, 0]), np.uint64(bits[row, 1]), np.uint64(bits[row, 2])
        key = (x * np.uint64(0x9E3779B97F4A7C15)) ^ (y * np.uint64(0xC2B2AE3D27D4EB4F)) ^ (z * np.uint64(0x165667B19E3779F9))
        slot = np.int64((key ^ (key >> np.uint64(29))) & np.uint64(size - 1))
        while True:
            held = np.int64(table[slot])
            if held == 0:
                table[slot] = row + 1
                break
            other = held - 1
            if bits[other, 0] == bits[row, 0] and bits[other, 1] == bits[row, 1] and bits[other, 2] == bits[row, 2]:
                repeated[row] = True
                break
            slot = (slot + 1) & (size - 1)
    return repeated
