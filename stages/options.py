"""The base of every stage's typed options: unknown keys are refused and a value never changes.

Each stage module defines `Options(StageOptions)`; its defaults are the product's defaults, and
`pipeline.config.PipelineConfig` is composed of these models (no second set of defaults).
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any, TypeVar

from pydantic import BaseModel, ConfigDict, ValidationError


class StageOptions(BaseModel):
    """A stage's settings: keyword construction, validation on creation, frozen, no extra keys."""

    model_config = ConfigDict(extra="forbid", frozen=True)


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
