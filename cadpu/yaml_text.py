"""YAML as the project's configuration files are read: PyYAML's safe loader, with two changes.

- Exponent numbers are numbers, as in YAML 1.2: `1e-3` and `5E4`. PyYAML follows YAML 1.1, whose
  floats need a dot (`1.0e-3`), and reads `1e-3` as text, which type checks then refuse.
- A key given twice in one mapping is an error naming both lines. PyYAML keeps the last value
  silently, so a second `upsample:` section, or a setting pasted in twice, undid the first without
  a word. A key that overrides one merged in (`<<: *base`) is not given twice.
"""

from __future__ import annotations

import re

import yaml
from yaml.composer import ComposerError

MERGE_TAG = "tag:yaml.org,2002:merge"


class ConfigLoader(yaml.SafeLoader):
    """`yaml.SafeLoader` with YAML 1.2 exponent floats and duplicate keys refused (module docstring)."""

    def compose_mapping_node(self, anchor: str | None) -> yaml.MappingNode:
        # checked as written, before any merge key is flattened into the mapping
        node = super().compose_mapping_node(anchor)
        first_line: dict[tuple[str, str], int] = {}
        for key_node, _ in node.value:
            if not isinstance(key_node, yaml.ScalarNode) or key_node.tag == MERGE_TAG:
                continue
            key = (key_node.tag, key_node.value)
            if key in first_line:
                raise ComposerError(None, None, f"key {key_node.value!r} given twice (first on line {first_line[key]})",
                                    key_node.start_mark)
            first_line[key] = key_node.start_mark.line + 1
        return node


ConfigLoader.add_implicit_resolver(
    "tag:yaml.org,2002:float", re.compile(r"^[-+]?(?:[0-9]+\.?[0-9]*|\.[0-9]+)[eE][-+]?[0-9]+$"),
    list("-+0123456789."))


def read_yaml(text: str) -> object:
    """Parse YAML text with `ConfigLoader`.

    Raises:
        yaml.YAMLError (its `problem_mark` the line and column) when the text is not YAML, or
        gives a key twice in one mapping.
    """
    return yaml.load(text, Loader=ConfigLoader)  # noqa: S506 - a SafeLoader subclass


def describe_error(error: yaml.YAMLError) -> str:
    """One line for a YAML error: "at line L, column C (problem)" where the error marks a place,
    else its first line."""
    where = getattr(error, "problem_mark", None)
    at = f"at line {where.line + 1}, column {where.column + 1} " if where is not None else ""
    problem = getattr(error, "problem", None) or str(error).splitlines()[0]
    return f"{at}({problem})"
