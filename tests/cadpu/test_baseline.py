import numpy as np

from cadpu.baseline import midpoint_upsample


def test_midpoints_stay_on_a_plane_and_count_is_r_times() -> None:
    rng = np.random.default_rng(0)
    plane = np.c_[rng.uniform(-1, 1, (256, 2)), np.zeros(256)]
    out, parents = midpoint_upsample(plane, 4)
    assert out.shape == (1024, 3)
    assert np.abs(out[:, 2]).max() < 1e-9
    assert np.bincount(parents).tolist() == [4] * 256
