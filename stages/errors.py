"""Errors raised by stages: each names the stage and the file (or frame) it concerns."""

from __future__ import annotations


class StageError(RuntimeError):
    """A stage could not process its input.

    Attributes:
        stage: stage name ("load", "ground", "tile", "upsample", "stitch", "write").
        source: the file or frame key concerned ("" when none).
        reason: what was wrong, in words a user can act on.
        points_in: the points the frame held when the stage failed (0 when it had none yet, a
            failure at load): what its report counts in (`pipeline.chain.Step` sets it).
    """

    def __init__(self, stage: str, source: str, reason: str) -> None:
        self.stage = stage
        self.source = str(source)
        self.reason = reason
        self.points_in = 0
        where = f" {self.source}:" if self.source else ""
        super().__init__(f"[{stage}]{where} {reason}")

    def __reduce__(self):  # keep the fields when pickled across Dask workers
        return (type(self), (self.stage, self.source, self.reason), {"points_in": self.points_in})


def first_line(error: BaseException) -> str:
    """An error's message up to its first line break ("" for none): many library errors run over
    paragraphs, and the tool's messages are one line."""
    text = str(error).strip()
    return text.splitlines()[0] if text else ""


class InputError(StageError):
    """Bad input data (a truncated .bin, NaN values, a missing calibration file, ...)."""
