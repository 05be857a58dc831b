"""The frame record and the checks every stage's `run` makes of its arguments."""

from __future__ import annotations

import numpy as np
import pytest

from stages import ground, stitch, tile, upsample, write
from stages.errors import StageError
from stages.frame import Frame


def _frame(columns: int = 4) -> Frame:
    points = np.random.default_rng(0).normal(size=(600, columns)).astype(np.float32) * 5
    return Frame(points=points, dataset="bin", sequence="s", index=0)


def test_stages_take_their_options_as_a_mapping_of_their_keys() -> None:
    # an AttributeError ('dict' object has no attribute 'method') before
    assert ground.run(_frame(), {"method": "ransac"}).ground is not None
    with pytest.raises(ValueError, match=r"ground.run: options nosuch: Extra inputs are not permitted"):
        ground.run(_frame(), {"nosuch": 1})


@pytest.mark.parametrize("stage", [ground, tile, upsample, stitch, write])
def test_another_stages_options_or_a_non_frame_are_refused_naming_the_stage(stage) -> None:
    name = stage.__name__.rpartition(".")[2]
    with pytest.raises(TypeError, match=rf"{name}.run: options must be stages.{name}.Options or a mapping"):
        stage.run(_frame(), tile.Options() if stage is not tile else ground.Options())
    with pytest.raises(TypeError, match=rf"{name}.run takes a stages.frame.Frame, got numpy.ndarray "
                                        r"\(stages.load.frame_from_points makes one"):
        stage.run(_frame().points)


def test_a_frame_of_three_columns_is_refused_by_the_first_stage_that_reads_its_fields() -> None:
    # ground and tile accepted it and stitch failed with an IndexError inside numpy (a new-user trial)
    with pytest.raises(StageError, match=r"\[tile\] .*frame.points has shape \(600, 3\), not \(N, 4\)"):
        tile.run(ground.run(_frame(columns=3)))
