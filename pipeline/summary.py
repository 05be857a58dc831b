"""What a run did, per frame and in total: printed as a table, written as JSON, mapped to an exit code.

Exit codes (documented in the README for schedulers):
    0  every selected frame is done (processed now, replaced, or skipped as already complete);
    2  bad configuration, input location, weights or cluster settings (nothing was processed);
    3  some frames failed, or the summary could not be written (the others' outputs are complete);
    4  another run is writing to the output folder (nothing was processed);
    130 / 143  interrupted by SIGINT / SIGTERM (the summary lists the frames done so far);
    1  the tool itself crashed (a bug: please report it).
"""

from __future__ import annotations

import json
import statistics
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any, Literal

from stages.temporaries import file_in_the_way, replace_atomically

EXIT_OK = 0
EXIT_CRASH = 1
EXIT_BAD_CONFIG = 2
EXIT_FRAMES_FAILED = 3
EXIT_OUTPUT_BUSY = 4
#: 128 + the signal's number, as a shell reports a process the signal ended.
EXIT_INTERRUPTED = {"SIGINT": 130, "SIGTERM": 143}

#: The stages of a frame's journey, in order (`pipeline.chain`); the keys of `FrameReport.timings`.
STAGES = ("load", "ground", "tile", "upsample", "stitch", "snap", "fill", "write")

#: done: processed in this run; replaced: processed in place of outputs made with another
#: configuration or model (`reason`); skipped: complete on disk already; failed: see `error`;
#: interrupted: not reached before a signal stopped the run.
Status = Literal["done", "replaced", "skipped", "failed", "interrupted"]


class SummaryWriteError(RuntimeError):
    """The run summary could not be written (a full disk, a read-only folder): the message names
    the file and the reason in one line; `summary` is the run's summary, for printing."""

    def __init__(self, message: str, summary: RunSummary) -> None:
        super().__init__(message)
        self.summary = summary


class Terminated(BaseException):
    """Raised in the main thread on SIGTERM (see `pipeline.cli`), like KeyboardInterrupt on SIGINT."""


#: The counts of a `FrameReport` that a frame's stored files record (`pipeline.resume.skipped_report`).
STORED_COUNTS = ("points_in", "points_out", "ground", "generated", "ground_filled", "dropped")


@dataclass
class FrameReport:
    """The outcome of one frame.

    points_in: points read from the scan (also for a frame that failed after load); points_out:
    points written (for a skipped frame, and for
    a failed or interrupted one whose earlier complete outputs stay in the folder, those its stored
    files hold; otherwise 0 for a failed or interrupted one); outputs: the frame's files in the
    folder after the run, by format ({} when it has none);
    ground / generated: how many output points are ground / generated (the network's and the
    ground fill's); ground_filled: generated ground points (`stages.ground_fill`);
    dropped: generated points removed by ring snapping or the range check (not written);
    timings: seconds per stage name; error: "[stage] file: reason" when failed; reason: why a
    frame was replaced ("source changed", "config changed", "model changed", "config not
    recorded", "model not recorded", "timestamp changed", "pose changed", "stored files damaged").
    """

    key: str
    dataset: str
    sequence: str
    index: int
    status: Status
    source: str = ""
    points_in: int = 0
    points_out: int = 0
    ground: int = 0
    generated: int = 0
    ground_filled: int = 0
    dropped: int = 0
    timings: dict[str, float] = field(default_factory=dict)
    outputs: dict[str, str] = field(default_factory=dict)
    notes: list[str] = field(default_factory=list)
    error: str | None = None
    failed_stage: str | None = None
    reason: str | None = None


@dataclass
class RunSummary:
    """All frames of one run plus its settings and wall time (seconds)."""

    frames: list[FrameReport]
    wall_seconds: float
    config_hash: str
    model_checksum: str
    ratio: int
    #: The most workers the cluster had running during the run (workers that joined later count)
    workers: int
    scheduler: str
    output_dir: str
    #: The signal that stopped the run ("SIGINT" or "SIGTERM"), None when it ran to its end.
    interrupted_by: str | None = None
    #: Why the run's record in OUT/runs/ could not be written (None when it was): exit status 3.
    record_missing: str | None = None
    #: Why OUT/summary.json could not be written (None when it was), as the run's record says it:
    #: exit status 3.
    summary_missing: str | None = None
    #: The settings `config_hash` stands for (`PipelineConfig.output_settings`).
    output_settings: dict[str, Any] = field(default_factory=dict)

    @property
    def interrupted(self) -> bool:
        return self.interrupted_by is not None

    def count(self, status: Status) -> int:
        return sum(1 for frame in self.frames if frame.status == status)

    @property
    def exit_code(self) -> int:
        """The process's exit status for this run: 130 / 143 when SIGINT / SIGTERM stopped it, else 3
        when a frame failed or was not done (the cluster lost it) or the run's record in OUT/runs/
        or summary.json could not be written, else 0."""
        if self.interrupted_by is not None:
            return EXIT_INTERRUPTED[self.interrupted_by]
        failed = self.count("failed") or self.count("interrupted") or self.record_missing or self.summary_missing
        return EXIT_FRAMES_FAILED if failed else EXIT_OK

    def stage_medians_ms(self) -> dict[str, float]:
        """Median milliseconds per stage over the frames processed in this run."""
        medians = {}
        for stage in STAGES:
            values = [f.timings[stage] for f in self.frames if stage in f.timings]
            if values:  # the mean of the middle two for an even count (it took the upper one)
                medians[stage] = 1000.0 * statistics.median(values)
        return medians

    def to_dict(self) -> dict[str, Any]:
        """`totals()` with every frame's report ("frames"): what summary.json holds."""
        return {**self.totals(), "frames": [asdict(f) for f in self.frames]}

    def totals(self) -> dict[str, Any]:
        """The counts, times and settings of the run, without the per-frame reports (which
        dataclasses.asdict copies one by one: seconds for a rerun of tens of thousands of frames)."""
        done = [f for f in self.frames if f.status in ("done", "replaced")]
        on_disk = [f for f in self.frames if f.outputs]
        return {
            "frames_total": len(self.frames),
            "frames_done": len(done),
            "frames_replaced": self.count("replaced"),
            "frames_skipped": self.count("skipped"),
            "frames_failed": self.count("failed"),
            "frames_interrupted": self.count("interrupted"),
            "interrupted": self.interrupted,
            "interrupted_by": self.interrupted_by,
            "points_in": sum(f.points_in for f in done),
            "points_out": sum(f.points_out for f in done),
            "points_in_on_disk": sum(f.points_in for f in on_disk),
            "points_out_on_disk": sum(f.points_out for f in on_disk),
            "wall_seconds": round(self.wall_seconds, 3),
            "stage_median_ms": {k: round(v, 1) for k, v in self.stage_medians_ms().items()},
            "exit_code": self.exit_code,
            "record_missing": self.record_missing,
            "summary_missing": self.summary_missing,
            "config_hash": self.config_hash,
            "output_settings": self.output_settings,
            "model_checksum": self.model_checksum,
            "ratio": self.ratio,
            "workers": self.workers,
            "scheduler": self.scheduler,
            "output_dir": self.output_dir,
        }

    def write_json(self, path: Path, skipped_frames: bool = True) -> Path:
        """Write the summary atomically (a temporary beside it, `stages.temporaries`, then a
        rename), with the mode of any new file (0666 less the umask, like the data files), and
        return the path. Without `skipped_frames`, the frames list leaves out the skipped ones
        but those with a note, of what the run did beside them or could not check (the totals
        still count them all): the run's record in OUT/runs/, which a scheduled rerun of a
        large set would otherwise fill with the same finished frames every time.

        Raises:
            SummaryWriteError naming `path` when it cannot be written; nothing is left behind.
        """
        path = Path(path)
        listed = self.frames if skipped_frames else [frame for frame in self.frames
                                                     if frame.status != "skipped" or frame.notes]
        text = json.dumps({**self.totals(), "frames": [asdict(frame) for frame in listed]}, indent=2)

        def write(temporary: Path) -> None:
            with open(temporary, "x") as stream:
                stream.write(text)

        try:
            replace_atomically(path, write)
        except OSError as error:
            blocking = file_in_the_way(path.parent)
            why = f"{blocking} is a file, not a folder" if blocking else (error.strerror or str(error))
            what = "the run summary" if skipped_frames else "the run's record"
            raise SummaryWriteError(f"cannot write {what} {path} ({why})", self) from None
        return path

    def table(self, max_rows: int = 40) -> str:
        """A plain-text table: one row per frame this run did or did not finish (failed first; at
        most `max_rows`), then the totals. Finished frames it skipped are counted in the totals
        only (summary.json lists them), so a rerun that skips most of a large set prints a few
        lines, unless they carry a note (what the run changed beside them, or could not check); with
        no row to list, the totals line alone."""
        listed = (frame for frame in self.frames if frame.status != "skipped" or frame.notes)
        ordered = sorted(listed, key=lambda frame: (frame.status != "failed", frame.key))
        width = max([36, *(len(f.key) for f in ordered[:max_rows])])  # raw keys run to 38 characters
        header = f"{'frame':<{width}} {'status':<11} {'in':>8} {'out':>9} " + " ".join(
            f"{stage:>8}" for stage in STAGES
        )
        lines = [header, "-" * len(header)] if ordered else []  # a rerun with nothing to list: the totals alone
        for frame in ordered[:max_rows]:
            cells = " ".join(
                f"{1000 * frame.timings[s]:>6.0f}ms" if s in frame.timings else f"{'':>8}" for s in STAGES
            )
            lines.append(
                f"{frame.key:<{width}} {frame.status:<11} {frame.points_in:>8} {frame.points_out:>9} {cells}"
            )
            if frame.error:
                lines.append(f"    error: {frame.error}")
            if frame.reason:
                lines.append(f"    replaced: {frame.reason}")
            lines += [f"    note: {note}" for note in frame.notes]
        if len(ordered) > max_rows:
            lines.append(f"... {len(ordered) - max_rows} more frames in the JSON summary")
        totals = self.totals()
        if ordered:
            lines.append("-" * len(header))
        lines.append(
            f"done {totals['frames_done']}"
            + (f" ({totals['frames_replaced']} replaced)" if totals["frames_replaced"] else "")
            + f", skipped {totals['frames_skipped']}, failed {totals['frames_failed']}"
            + (f", interrupted {totals['frames_interrupted']}" if self.interrupted or totals["frames_interrupted"] else "")
            + f" of {totals['frames_total']} frames; points in "
            f"{totals['points_in']}, out {totals['points_out']}"
            + (f" (the selected frames' files, with those not done now: in {totals['points_in_on_disk']}, out "
               f"{totals['points_out_on_disk']})" if totals["points_out_on_disk"] != totals["points_out"] else "")
            + f"; {self.wall_seconds:.1f} s "
            + (f"on {self.workers} worker(s)" if self.workers else
               "(stopped before the cluster started)" if self.interrupted else
               f"(cluster not contacted: {unstarted})" if (unstarted := _reason_after(self.scheduler,
                                                                                   "(not contacted: ")) else
               f"(no cluster started: {unstarted})" if (unstarted := _unstarted_reason(self.scheduler)) else
               f"(no worker ran a frame: {idle})" if (idle := _reason_after(self.scheduler, "(contacted: ")) else
               "(no worker ran a frame: the cluster had none)" if totals["frames_interrupted"] else
               "(no cluster started: nothing to process)" if totals["frames_done"] + totals["frames_failed"] == 0 else
               "(no worker ran a frame: the cluster failed)")
        )
        return "\n".join(lines)


def _unstarted_reason(scheduler: str) -> str | None:
    """Why the run started or contacted no cluster, from its `scheduler` text ("none (nothing to
    do)", "tcp://... (not contacted: no frame needed the network)"); None when it did."""
    return _reason_after(scheduler, "none (") or _reason_after(scheduler, "(not contacted: ")


def _reason_after(scheduler: str, opening: str) -> str | None:
    """The text between `opening` and the closing parenthesis that ends `scheduler`, or None."""
    if opening in scheduler and scheduler.endswith(")"):
        return scheduler[scheduler.index(opening) + len(opening):-1]
    return None
