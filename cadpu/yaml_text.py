"""YAML as the project's configuration files are read: PyYAML's safe loader, with two changes.

- Exponent numbers are numbers, as in YAML 1.2: `1e-3` and `5E4`. PyYAML follows YAML 1.1, whose
  floats need a dot (`1.0e-3`), and reads `1e-3` as text, which type checks then refuse.
- A key given twice in one mapping is an error naming both lines. PyYAML keeps the last value
  silently, so a second `upsample:` section, or a setting pasted in twice, undid the first without
  a word.
"""

from __future__ import annotations

import re

import yaml
from yaml.constructor import ConstructorError


class ConfigLoader(yaml.SafeLoader):
    """`yaml.SafeLoader` with YAML 1.2 exponent floats and duplicate keys refused (module docstring)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict:
        first_line: dict[object, int] = {}
        for key_node, _ in node.value:  # the mapping's own keys: merged ones (`<<: *base`) may be overridden
            if key_node.tag == "tag:yaml.org,2002:merge":
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                seen = key in first_line
            except TypeError:  # an unhashable key: the safe loader's own error names it
                break
            if seen:
                raise ConstructorError(None, None, f"key {key!r} given twice (first on line {first_line[key]})",
                                       key_node.start_mark)
            first_line[key] = key_node.start_mark.line + 1
        return super().construct_mapping(node, deep)


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
