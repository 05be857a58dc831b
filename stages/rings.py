"""The ring structure of a LiDAR scan stored in KITTI's point order: which laser (ring) each point
came from, read from the order alone, and the thinning of a scan to one ring in `ratio`.

KITTI's .bin files store a scan ring by ring from the top laser (+2 degrees) down to the bottom
one, and within a ring counter-clockwise seen from above (azimuth atan2(y, x) increasing), starting
just above 0, through +-180 degrees behind the sensor, and ending just below 0 (checked on the six
scans of odometry sequence 00; `cadpu.synthetic.lidar` simulates the same order). So a new ring
starts where the azimuth wraps from negative to non-negative. That needs the scan in KITTI's
sensor frame, x forward: a scan turned about z (another yaw convention) is cut into rings mid-ring,
where its azimuth passes 0, and must be turned back first. Where its first points lie tells
nothing (a top laser with no return ahead starts late in KITTI's frame too), and the steps from
one laser to the next at the true cut are as many as those at a wall's edge.

Frames: the sensor (Velodyne) frame has x forward, y left, z up, metres, like KITTI's.
"""

from __future__ import annotations

import numbers

import numpy as np

from .errors import InputError
from .wording import counted

#: The most lasers a spinning LiDAR has (128-beam sensors): a point order showing more rings is not
#: a scan stored ring by ring (a shuffled scan "wraps" at every other point).
MAX_LASERS = 128
#: A scan whose steps along the point order turn backward more often than this is not in KITTI's
#: order (KITTI's: 0.30-0.36% of steps, jitter; the same scans reversed: 99.6-99.9%;
#: docs/results.md, "Ring order").
MAX_BACKWARD_SHARE = 0.5

#: Backward azimuth steps up to this size count as jitter within a ring, not as a new ring. The
#: real scans of sequence 00 step backwards by up to 7 degrees (near objects seen from lasers
#: that sit off the sensor axis).
RING_JITTER = np.radians(20.0)


def recover_rings(points: np.ndarray) -> np.ndarray:
    """Ring (laser) index of every point of a scan stored in KITTI order, from the order alone.

    Within a ring the azimuth atan2(y, x) turns counter-clockwise from just above 0 round to just
    below 0; the next ring starts where it wraps from negative to non-negative. The azimuth is
    unwrapped along the point order, treating every step as a forward turn except backward
    steps of less than `RING_JITTER` (20 degrees), which are jitter; a ring boundary is where the
    unwrapped azimuth passes the next multiple of 360 degrees. This also splits rings whose
    returns lie on one side only (the azimuth then jumps back by more than 20 degrees without
    passing 0), ignores the -180 -> +180 degree seam behind the sensor, and, by keeping ring ids
    non-decreasing, does not flicker when near points jitter across 0. A point that jitters
    across 0 just before its ring ends is counted in the next ring.

    On the six real scans of KITTI odometry sequence 00 it finds all 64 rings (docs/results.md).

    Args:
        points: (N, 3+) points in KITTI order (x, y first; further columns are ignored).

    Returns:
        (N,) int64 ring numbers 0, 1, ... (0 = the first ring stored, the top laser in KITTI).
        A ring without any return cannot be seen in the order and gets no number.
    """
    points = np.asarray(points)
    if points.ndim != 2 or points.shape[1] < 2:
        raise ValueError(f"recover_rings: points must be (N, 3+), got shape {points.shape}")
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64)
    return rings_of_turns(*azimuth_turns(points))


def azimuth_turns(points: np.ndarray) -> tuple[float, np.ndarray]:
    """The first point's azimuth and each step's turn along the point order (radians), every step
    read as a forward (counter-clockwise) turn but backward ones within `RING_JITTER`, which stay
    negative: what `recover_rings` and `backward_step_share` read the order by.

    Args:
        points: (N, 2+) points in their stored order (x, y first), N >= 0.

    Returns:
        (first azimuth in [-RING_JITTER, 2 pi - RING_JITTER), (N - 1,) float64 turns).

    Raises:
        ValueError: a point with a NaN or infinite x or y.
    """
    if len(points) == 0:
        return 0.0, np.zeros(0)
    x, y = np.asarray(points[:, 0], np.float64), np.asarray(points[:, 1], np.float64)
    bad = ~(np.isfinite(x) & np.isfinite(y))
    if bad.any():  # a NaN turned every later turn into NaN, and every later point into one ring
        raise ValueError(f"rings: {counted(int(bad.sum()), 'point')} with NaN or infinite x or y (the first at index "
                         f"{int(np.argmax(bad))}); the ring order cannot be read past them")
    azimuth = np.arctan2(y, x)
    turn = 2 * np.pi
    first = float(np.mod(azimuth[0] + RING_JITTER, turn) - RING_JITTER)
    return first, np.mod(np.diff(azimuth) + RING_JITTER, turn) - RING_JITTER


def rings_of_turns(first: float, turns: np.ndarray) -> np.ndarray:
    """(N,) int64 ring numbers of the N >= 1 points whose `azimuth_turns` these are (`recover_rings`)."""
    turn = 2 * np.pi
    unwrapped = first + np.concatenate([[0.0], np.cumsum(turns)])
    # a scan whose first points jitter just below 0 still starts ring 0: clamp at 0
    ring = np.maximum(np.floor(unwrapped / turn).astype(np.int64), 0)
    return np.maximum.accumulate(ring)


def rings_and_backward_share(points: np.ndarray) -> tuple[np.ndarray, float]:
    """`recover_rings` and `backward_step_share` of the same points from one reading of their
    azimuths: what a check of a scan's ring order needs.

    Args:
        points: (N, 2+) points in their stored order (x, y first).

    Returns:
        (N,) int64 ring ids, and the share of backward steps (0 for fewer than 2 points).
    """
    if len(points) == 0:
        return np.zeros(0, dtype=np.int64), 0.0
    first, turns = azimuth_turns(points)
    return rings_of_turns(first, turns), share_backward(turns)


def backward_step_share(points: np.ndarray) -> float:
    """The share of steps along the point order whose azimuth turns clockwise (backward): few in
    KITTI's order (jitter), nearly all in a scan stored in reverse or turning clockwise
    (docs/results.md, "Ring order").

    Args:
        points: (N, 2+) points in their stored order (x, y first).
    """
    return share_backward(azimuth_turns(points)[1])


def share_backward(turns: np.ndarray) -> float:
    """The share of negative `azimuth_turns` steps (`backward_step_share`); 0 for none."""
    return float(np.count_nonzero(turns < 0) / len(turns)) if len(turns) else 0.0


def keep_rings(points: np.ndarray, rings: np.ndarray, ratio: int = 4, offset: int = 0) -> np.ndarray:
    """The points of rings offset, offset + ratio, offset + 2 * ratio, ... in their original order.

    Args:
        points: (N, C) any per-point array. rings: (N,) ring ids (e.g. from `recover_rings`).
        ratio: keep one ring in `ratio` (4 turns 64 rings into 16). offset: first ring kept.

    Returns:
        (M, C) the kept rows of `points`.
    """
    whole = all(isinstance(n, numbers.Integral) and not isinstance(n, bool) for n in (ratio, offset))
    if not whole or ratio < 1 or not 0 <= offset < ratio:  # 2.5 kept rings 0, 5, 10, ... without a word
        raise ValueError(f"keep_rings: need whole numbers ratio >= 1 and 0 <= offset < ratio, got ratio={ratio!r}, "
                         f"offset={offset!r}")
    rings = np.asarray(rings)
    if len(rings) != len(points):
        raise ValueError(f"keep_rings: {len(points)} points but {len(rings)} ring ids")
    return points[(rings - offset) % ratio == 0]


#: The rings of the scans that thin themselves into their own training and evaluation pairs: KITTI's
#: Velodyne HDL-64E (eval-kitti, finetune). A scan of fewer rings would teach or score another task
#: (16 rings thinned to 4).
HDL64E_RINGS = 64


def hdl64e_rings(points: np.ndarray, ratio: int, stage: str, source: str, use: str) -> np.ndarray:
    """`full_scan_rings` of a scan that must hold KITTI's `HDL64E_RINGS` rings.

    Args:
        use: what needs them, for the error ("the evaluation", "fine-tuning").

    Raises:
        InputError(stage, source, ...) as `full_scan_rings` does, and when the order shows another
        number of rings.
    """
    rings = full_scan_rings(points, ratio, stage, source)
    found = int(rings.max()) + 1
    if found != HDL64E_RINGS:
        raise InputError(stage, source, f"{found} laser rings found in the point order; {use} takes full "
                                        f"{HDL64E_RINGS}-ring scans (KITTI's HDL-64E), thinned to {HDL64E_RINGS // ratio}")
    return rings


def full_scan_rings(points: np.ndarray, ratio: int, stage: str, source: str) -> np.ndarray:
    """Ring ids of a full scan that a tool thins to one ring in `ratio` (`recover_rings`), checked
    to be a scan stored ring by ring.

    Args:
        points: (N, 3+) scan in stored order. ratio: the thinning step. stage, source: for the error.

    Returns:
        (N,) int64 ring ids.

    Raises:
        InputError(stage, source, ...) when the order shows fewer than 2 * ratio rings or more than
        `MAX_LASERS`, or turns backward at more than `MAX_BACKWARD_SHARE` of its steps (a reversed
        scan): not a full scan in KITTI order.
    """
    rings, backward = rings_and_backward_share(points)
    found = int(rings.max()) + 1 if len(rings) else 0
    if not 2 * ratio <= found <= MAX_LASERS:
        raise InputError(stage, source, f"{found} laser rings found in the point order (needs {2 * ratio} to "
                                        f"{MAX_LASERS}: a full scan stored ring by ring, in KITTI order)")
    if backward > MAX_BACKWARD_SHARE:
        raise InputError(stage, source, f"{backward:.0%} of the steps along the point order turn backward (KITTI's "
                                        f"order: under 1%): the scan is stored in reverse or turning the other way")
    return rings
