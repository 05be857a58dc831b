"""The base of every stage's typed options: unknown keys are refused and a value never changes.

Each stage module defines `Options(StageOptions)`; its defaults are the product's defaults, and
`pipeline.config.PipelineConfig` is composed of these models (no second set of defaults).
"""

from __future__ import annotations

from pydantic import BaseModel, ConfigDict


class StageOptions(BaseModel):
    """A stage's settings: keyword construction, validation on creation, frozen, no extra keys."""

    model_config = ConfigDict(extra="forbid", frozen=True)
