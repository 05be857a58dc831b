"""The base of every stage's typed options: unknown keys are refused and a value never changes.

Each stage module defines `Options(StageOptions)`; its defaults are the product's defaults, and
`pipeline.config.PipelineConfig` is composed of these models (no second set of defaults).
"""

from __future__ import annotations

import types
import typing
from collections.abc import Mapping
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError, ValidationInfo, field_validator


def refuse_empty_path(value: object, key: str) -> object:
    """`value` unchanged, unless it is empty text, which a path would read as the working folder
    (a script's unset variable: `kitti-pu run "$DATA"`): ValueError naming `key`."""
    if isinstance(value, str) and not value.strip():
        raise ValueError(f"{key} is empty (an unset variable?); give a path, '.' for the working folder")
    return value


def _takes_bool(annotation: Any) -> bool:
    """Whether a field's type admits a bool (bool itself, a union with it, Any)."""
    if annotation is bool or annotation is Any:
        return True
    if typing.get_origin(annotation) in (typing.Union, types.UnionType):
        return any(_takes_bool(arg) for arg in typing.get_args(annotation))
    return False


class StrictSwitches(BaseModel):
    """Refuses true/false (and YAML's yes/no/on/off) for a setting that is not a switch: pydantic
    would take them as 1 and 0, so `snap.range_tolerance=false`, meant as "off" (which is null),
    set the strictest check instead."""

    @field_validator("*", mode="before")
    @classmethod
    def _no_bool_for_numbers(cls, value: Any, info: ValidationInfo) -> Any:
        field = cls.model_fields.get(info.field_name or "")
        if isinstance(value, bool) and field is not None and not _takes_bool(field.annotation):
            raise ValueError(f"{str(value).lower()} is not a value of this setting (a switch's "
                             "true/false; null is 'off' where a setting has one)")
        return value


class StageOptions(StrictSwitches):
    """A stage's settings: keyword construction, validation on creation, frozen, no extra keys, no
    NaN or infinite numbers (`tile.vertical_scale: .inf` passed `gt=0`, then failed every frame as
    if its scan were bad)."""

    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


OptionsT = TypeVar("OptionsT", bound=StageOptions)


def stage_options(options: Any, kind: type[OptionsT], stage: str) -> OptionsT:
    """`options` as `kind`, the Options of `stage`: itself, or built from a mapping of its keys
    (`ground.run(frame, {"method": "ransac"})`).

    Raises:
        TypeError: anything else (another stage's Options, a string), naming the stage and what it takes.
        ValueError: a mapping with an unknown key or a bad value, naming the stage.
    """
    if isinstance(options, kind):
        return options
    if isinstance(options, Mapping):
        try:
            return kind(**options)
        except ValidationError as error:
            first = error.errors()[0]
            where = ".".join(str(part) for part in first["loc"])
            raise ValueError(f"{stage}.run: options {where}: {first['msg']}") from None
    raise TypeError(f"{stage}.run: options must be stages.{stage}.Options or a mapping of its keys, "
                    f"got {type(options).__module__}.{type(options).__qualname__}")
