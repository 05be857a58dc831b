"""The HDL-64E of KITTI's car as measured on the six scans of KITTI odometry sequence 00 by
`bench/sim_vs_real.py` (docs/results.md, "Simulated against real scans"): the defaults of
`cadpu.synthetic.lidar.LidarModel`. Angles in degrees, lengths in metres, the sensor frame (x
forward, y left, z up); ring 0 is the top laser, stored first.
"""

from __future__ import annotations

import numpy as np

#: Far-field elevation of each laser of the HDL-64E of KITTI's car, degrees, ring 0 first: the
#: cones fitted to the six scans of odometry sequence 00 once the car's motion is undone
#: (z = h_block + rho tan(elevation), median over the scans; `bench/sim_vs_real.py --per-ring`).
KITTI_ELEVATIONS_DEG = np.array([
    1.939, 1.576, 1.307, 0.873, 0.581, 0.181, -0.089, -0.453, -0.804, -1.204, -1.497, -1.837, -2.213, -2.554,
    -2.881, -3.243, -3.548, -3.946, -4.227, -4.601, -4.929, -5.268, -5.631, -5.981, -6.353, -6.704, -7.030,
    -7.321, -7.716, -8.098, -8.353, -8.758, -9.126, -9.680, -10.175, -10.588, -11.083, -11.736, -12.259,
    -12.714, -13.201, -13.651, -14.225, -14.785, -15.384, -15.861, -16.390, -16.775, -17.418, -17.970, -18.576,
    -19.059, -19.592, -20.013, -20.513, -21.086, -21.627, -22.255, -22.768, -23.186, -23.671, -24.321, -24.872,
    -25.368])
#: Height of each block's lasers above the scan's origin on the sensor axis, metres (upper, lower),
#: fitted with the elevations above.
KITTI_BLOCK_OFFSETS_M = (0.2074, 0.1453)
#: Where KITTI's own car and sensor rack hide the ground from the lowest lasers: (azimuth from,
#: azimuth to, elevation below), degrees; a ray whose azimuth (0 ahead, counter-clockwise, in
#: [0, 360)) lies in [from, to) and whose elevation is below the third number gets no return. Made
#: from the six scans of sequence 00: the 2-degree sectors where every ring from some laser down
#: has returns in fewer than half of its firings, in all six scans' median (`bench/sim_vs_real.py`,
#: rows "returns/ring/firing"); the threshold lies halfway between that laser and the one above.
KITTI_EGO_SHADOW = (
    (0, 10, -21.93), (10, 16, -22.50), (16, 18, -23.42), (18, 20, -24.58), (26, 28, -25.10), (28, 30, -23.98),
    (32, 34, -24.58), (34, 36, -25.10), (36, 38, -23.98), (128, 132, -25.10), (132, 136, -21.34),
    (136, 138, -25.10), (138, 140, -24.58), (140, 142, -25.10), (142, 144, -23.98), (146, 148, -24.58),
    (148, 154, -25.10), (154, 156, -23.98), (156, 160, -21.93), (160, 162, -19.79), (162, 164, -17.09),
    (164, 166, -19.31), (166, 170, -19.79), (170, 196, -19.31), (196, 198, -19.79), (198, 200, -17.68),
    (200, 202, -19.31), (202, 204, -20.25), (204, 206, -21.34), (206, 208, -22.50), (208, 210, -23.42),
    (210, 214, -24.58), (214, 216, -25.10), (218, 224, -25.10), (224, 228, -24.58), (228, 232, -25.10),
    (232, 234, -21.93), (234, 236, -21.34), (236, 238, -22.50), (280, 286, -25.10), (320, 324, -25.10),
    (324, 326, -23.42), (326, 328, -24.58), (328, 330, -25.10), (330, 332, -23.98), (340, 342, -25.10),
    (342, 344, -23.98), (344, 346, -22.96), (346, 348, -22.50), (348, 360, -21.93),
)
#: Forward speed of KITTI's car in the six scans, m/s (`bench/sim_vs_real.py`, row "ego speed").
KITTI_EGO_SPEED = 8.45
#: Each laser's constant range bias, metres, ring 0 first: on walls KITTI's rings sit off each
#: other along their beams, by the same amounts in every scan (`bench/scan_statistics.py`,
#: `ring_range_bias`; docs/results.md, "Simulated against real scans"). Rings 0-6, 8-16, 18 and
#: 20-23 are the median over the six scans of sequence 00 (each estimated in at least 4 of them,
#: relative to its neighbours); the other 43 lasers never see enough wall there, and hold draws of
#: a normal distribution with the measured rings' RMS, 4.4 cm (numpy default_rng(64)).
KITTI_RANGE_BIAS_M = np.array([
    0.054, -0.030, 0.040, -0.026, 0.032, -0.078, 0.065, -0.000, -0.011, 0.016, 0.055, -0.029, 0.032, 0.000,
    -0.011, 0.013, 0.072, 0.037, 0.083, -0.020, 0.036, -0.063, 0.023, -0.022, -0.008, 0.025, -0.008, -0.054,
    0.081, 0.017, -0.041, -0.082, 0.042, 0.009, 0.029, 0.075, 0.113, 0.001, 0.056, 0.010, -0.062, 0.059,
    0.012, 0.003, 0.013, -0.019, 0.087, 0.131, 0.064, -0.007, -0.064, 0.038, -0.031, -0.002, 0.039, -0.013,
    0.003, -0.011, -0.026, 0.038, -0.003, 0.064, -0.005, 0.026])


def kitti_vertical_offsets() -> np.ndarray:
    """(64,) height of each laser above the scan's origin, metres: `KITTI_BLOCK_OFFSETS_M` per block."""
    return np.repeat(np.asarray(KITTI_BLOCK_OFFSETS_M, dtype=np.float64), 32)
