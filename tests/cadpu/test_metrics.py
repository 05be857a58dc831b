import numpy as np
import pytest

from cadpu.metrics import (chamfer_distance, chamfer_from_distances, directed_distances, hausdorff_distance,
                           hausdorff_from_distances, voxel_f1)


def test_chamfer_and_hausdorff_known_answers() -> None:
    a = np.array([[0.0, 0, 0], [1, 0, 0]])
    b = np.array([[0.0, 0, 0], [1, 0, 0], [3, 0, 0]])
    # a->b: 0, 0; b->a: 0, 0, 2
    assert chamfer_distance(a, b) == pytest.approx(0.5 * (0 + 2 / 3))
    assert hausdorff_distance(a, b) == pytest.approx(2.0)


def test_metrics_from_distances_equal_the_metrics_of_the_points() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.normal(size=(200, 3)), rng.normal(size=(300, 3))
    a_to_b, b_to_a = directed_distances(a, b), directed_distances(b, a)
    assert chamfer_from_distances(a_to_b, b_to_a) == chamfer_distance(a, b)
    assert hausdorff_from_distances(a_to_b, b_to_a) == hausdorff_distance(a, b) == max(a_to_b.max(), b_to_a.max())
    assert hausdorff_from_distances(a_to_b, b_to_a, 95.0) == hausdorff_distance(a, b, 95.0)


def test_voxel_f1_known_answer() -> None:
    pred = np.array([[0.05, 0.05, 0.05], [0.15, 0.05, 0.05]])
    ref = np.array([[0.05, 0.05, 0.05], [0.55, 0.05, 0.05], [0.65, 0.05, 0.05], [0.75, 0.05, 0.05]])
    score = voxel_f1(pred, ref, 0.1)
    assert score.precision == pytest.approx(0.5)
    assert score.recall == pytest.approx(0.25)
    assert score.f1 == pytest.approx(2 * 0.5 * 0.25 / 0.75)


def test_voxel_f1_does_not_depend_on_where_the_clouds_sit() -> None:
    rng = np.random.default_rng(0)
    a, b = rng.uniform(0, 80, (20_000, 3)), rng.uniform(0, 80, (20_000, 3))
    local = voxel_f1(a, b)
    utm = np.array([5e5, 5.4e6, 300.0])  # a map frame: keys packed from the origin collided here
    assert voxel_f1(a + utm, b + utm) == pytest.approx(local)
    with pytest.raises(ValueError, match="span .* voxels on an axis"):  # two points 210 km apart scored F1 1.0
        voxel_f1(np.array([[0.0, 0.1, 0.0]]), np.array([[0.0, 0.0, 209_715.25]]))
