"""Tests of the stages' shared wording (stages.wording)."""

from __future__ import annotations

import numpy as np

from stages.load import frame_from_points
from stages.wording import counted


def test_counted_says_one_in_the_singular_and_any_other_count_in_the_plural() -> None:
    assert counted(1, "point") == "1 point"
    assert [counted(n, "point") for n in (0, 2)] == ["0 points", "2 points"]
    assert counted(1, "patch", "patches") == "1 patch" and counted(3, "patch", "patches") == "3 patches"


def test_a_note_about_one_point_says_one_point() -> None:
    # "1 points beyond 200 m dropped at load" (a library user's trial)
    points = np.random.default_rng(0).normal(size=(600, 4)).astype(np.float32) + [0, 0, 0, 5]
    points[:, :3] *= 10
    points[7, :3] = [500.0, 0.0, 0.0]
    frame = frame_from_points(points)
    assert any(note.startswith("1 point beyond 200 m dropped at load") for note in frame.notes), frame.notes
