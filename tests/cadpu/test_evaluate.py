"""Tests of the object-level evaluation's held-out sets (`cadpu.evaluate`)."""

from __future__ import annotations

import numpy as np

from cadpu.evaluate import held_out_cases
from cadpu.synthetic.shapes import FAMILIES


def test_held_out_meshes_from_an_offset_are_those_of_the_full_list() -> None:
    full = held_out_cases(5)
    later = held_out_cases(2, first=3)
    assert [c.name for c in later] == [c.name for c in full[3:]]
    for a, b in zip(later, full[3:]):
        assert np.array_equal(a.inputs, b.inputs)
        assert np.array_equal(a.mesh.vertices, b.mesh.vertices)
    # the shape families keep cycling with the absolute index
    assert [c.name.rsplit("-", 1)[0] for c in later] == [list(FAMILIES)[i % len(FAMILIES)] for i in (3, 4)]
