import numpy as np
import pytest

from cadpu.metrics import chamfer_distance, hausdorff_distance, voxel_f1


def test_chamfer_and_hausdorff_known_answers() -> None:
    a = np.array([[0.0, 0, 0], [1, 0, 0]])
    b = np.array([[0.0, 0, 0], [1, 0, 0], [3, 0, 0]])
    # a->b: 0, 0; b->a: 0, 0, 2
    assert chamfer_distance(a, b) == pytest.approx(0.5 * (0 + 2 / 3))
    assert hausdorff_distance(a, b) == pytest.approx(2.0)


def test_voxel_f1_known_answer() -> None:
    pred = np.array([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05]])
    ref = np.array([[0.05, 0.05, 0.05], [0.55, 0.05, 0.05], [0.65, 0.05, 0.05], [0.75, 0.05, 0.05]])
    score = voxel_f1(pred, ref, 0.1)
    assert score.precision == pytest.approx(0.5)
    assert score.recall == pytest.approx(0.25)
    assert score.f1 == pytest.approx(2 * 0.5 * 0.25 / 0.75)
