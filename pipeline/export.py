"""Finished frames written from their stored files, without the network: in the output formats
they lack, or in all of them with a new timestamp, pose or scan path (`RECORD_ONLY_REASONS`).

A user who adds a format to a finished folder (`output.formats: [parquet, ply]` where the runs so
far wrote Parquet) needs only each frame's stored cloud written again in the new format. A frame
qualifies when the files of another format are complete and record this run's scan,
configuration and model, as `pipeline.resume.decide` requires to skip them. Every format holds the
whole cloud (`stages.stored`), so the new files hold the same points, and the frame's stored
record with this run's id. Reading a file back and writing it takes tens of milliseconds; running
the network again took about a second per frame.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from pathlib import Path

import numpy as np
from pyarrow import ArrowException

from stages import load, write
from stages.errors import StageError
from stages.frame import Frame
from stages.stored import read_cloud

from .resume import MOVED_REASONS, decide, skipped_report, stored_metadata
from .summary import FrameReport


def stored_formats_to_export(ref: load.FrameRef, out_dir: Path, formats: tuple[str, ...], config_hash: str,
                             checksum: str, also_configs: tuple[str, ...] = (),
                             metadata: Callable[[], Mapping[str, str] | None] | None = None) -> tuple[str, ...]:
    """The formats whose complete files of `ref` this run would skip (the same scan, configuration,
    model and, with `metadata`, timestamp and pose: `pipeline.resume.decide`), Parquet first (the
    quickest to read), when the frame lacks complete files in one of `formats`; () when it lacks
    none, or has no such files (it is then done in full)."""
    wanted = write.output_paths(out_dir, ref.dataset, ref.sequence, ref.index, formats, ref.source)
    if all(write.is_complete({name: path}) for name, path in wanted.items()):
        return ()
    return matching_stored_formats(ref, out_dir, config_hash, checksum, also_configs, metadata)


def matching_stored_formats(ref: load.FrameRef, out_dir: Path, config_hash: str, checksum: str,
                            also_configs: tuple[str, ...] = (),
                            metadata: Callable[[], Mapping[str, str] | None] | None = None,
                            content: Callable[[], str] | None = None) -> tuple[str, ...]:
    """The formats, Parquet first, whose complete files of `ref` record this run's scan,
    configuration and model and, with `metadata`, timestamp and pose (`pipeline.resume.decide`);
    with `content`, also those whose scan has only moved or been touched since (`MOVED_REASONS`)."""
    found = []
    for name in write.FORMATS:
        stored = write.output_paths(out_dir, ref.dataset, ref.sequence, ref.index, (name,), ref.source)
        if not write.is_complete(stored):
            continue
        decision = decide(stored, config_hash, checksum, False, ref.fingerprint, also_configs, metadata, content)
        if decision.action == "skip" or decision.reason in MOVED_REASONS:
            found.append(name)
    return tuple(found)


#: Why a finished frame is replaced whose points would be the same: what it records of its scan
#: changed (its timestamp, its pose, or the path or time of a file with the same bytes), which no
#: stage reads but load and the writers (`export_frame` with `rewrite`).
RECORD_ONLY_REASONS = ("timestamp changed", "pose changed", *MOVED_REASONS)


def export_frame(ref: load.FrameRef, out_dir: Path, formats: tuple[str, ...], stored_formats: tuple[str, ...],
                 record_updates: Mapping[str, str], rewrite: bool = False) -> FrameReport | None:
    """Write `ref`'s frame in those of `formats` it lacks (with `rewrite`, in all of them), from the
    first of its `stored_formats` files that reads back whole.

    Args:
        ref: the frame. out_dir: the output folder. formats: the run's formats.
        stored_formats: formats of complete files to read (`stored_formats_to_export`).
        record_updates: values that replace the stored record's in the new files (the run's id;
            with `rewrite`, the timestamp and pose the dataset gives the frame now, and a moved
            scan's path and fingerprint).
        rewrite: write every one of `formats` again: a frame whose timestamp, pose or scan path
            changed (`RECORD_ONLY_REASONS`) gets its new record with the same points, without the
            network.

    Returns:
        The frame's report: "done", its counts from the stored record, a note saying what was
        written from what (a stored file of the run's formats that does not read back is written
        again too); "failed" naming the file when a new one cannot be written (nothing
        half-written stays). None when no stored file reads back (damaged inside, past the footer
        or header that made it look complete): the frame is then to be done in full.
    """
    paths = write.output_paths(out_dir, ref.dataset, ref.sequence, ref.index, formats, ref.source)
    missing = [name for name, path in paths.items() if rewrite or not write.is_complete({name: path})]
    for stored_format in stored_formats:
        stored_paths = write.output_paths(out_dir, ref.dataset, ref.sequence, ref.index, (stored_format,), ref.source)
        try:
            cloud = read_cloud(stored_format, stored_paths[stored_format])
        except (OSError, ValueError, ArrowException):
            if stored_format in formats and stored_format not in missing:  # damaged: written again from the next one that reads
                missing.append(stored_format)
            continue
        stored = stored_metadata(stored_paths)
        frame = Frame(points=np.empty((0, 4), np.float32), dataset=ref.dataset, sequence=ref.sequence,
                      index=ref.index, source=ref.source)
        try:
            write.write_frame(cloud, frame, out_dir, {}, tuple(missing), record={**stored, **record_updates})
        except StageError as error:
            return FrameReport(key=ref.key, dataset=ref.dataset, sequence=ref.sequence, index=ref.index,
                               status="failed", source=str(ref.source), error=str(error), failed_stage=error.stage)
        report = skipped_report(ref, paths, stored)
        report.status = "done"
        what = "its new record (timestamp, pose, scan path) written" if rewrite else "written"
        report.notes.append(f"{what} in {', '.join(missing)} from its {stored_format} file (the network was not run)")
        return report
    return None
