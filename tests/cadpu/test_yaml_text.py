"""cadpu.yaml_text: the safe loader with exponent numbers and duplicate keys refused."""

from __future__ import annotations

import pytest
import yaml

from cadpu.yaml_text import read_yaml


def test_exponent_numbers_are_numbers() -> None:
    assert read_yaml("lr: 1e-3\nsteps: 5E4\nname: e5\n") == {"lr": 0.001, "steps": 50000.0, "name": "e5"}


def test_a_key_given_twice_is_an_error_at_its_second_line() -> None:
    with pytest.raises(yaml.YAMLError, match=r"key 'b' given twice \(first on line 2\)") as info:
        read_yaml("a: 1\nb: 2\nc:\n  d: 1\nb: 3\n")
    assert info.value.problem_mark.line + 1 == 5
    with pytest.raises(yaml.YAMLError, match="key 'd' given twice"):  # in a nested mapping too
        read_yaml("c:\n  d: 1\n  d: 2\n")


def test_the_same_key_in_different_mappings_and_merge_keys_are_fine() -> None:
    assert read_yaml("a: {x: 1}\nb: {x: 2}\n") == {"a": {"x": 1}, "b": {"x": 2}}
    assert read_yaml("base: &b {x: 1, y: 2}\nmore:\n  <<: *b\n  y: 3\n")["more"] == {"x": 1, "y": 3}
    # a mapping that overrides a merged key, itself merged deeper down: flattened in place by the
    # outer merge before it was built, it was taken for a key given twice
    nested = read_yaml("defs:\n  inner: &b\n    <<: {seed: 0}\n    seed: 1\ntile:\n  <<: *b\n")
    assert nested == {"defs": {"inner": {"seed": 1}}, "tile": {"seed": 1}}
