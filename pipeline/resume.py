"""What a re-run does with a frame whose outputs may already exist: skip it, replace it, or do it.

A frame is skipped only when every output file is complete and each of its files records the same scan
(path, size and modification time: `stages.discovery.source_fingerprint`), the same output-relevant
configuration, the same model (weights checksum), and the timestamp and pose the dataset gives the
frame now (a corrected times.txt, oxts/ or poses/ file), as this run. Complete outputs made from
another scan, configuration, model or metadata, or that record no configuration or model, are
replaced, and the report says why. A scan of the same name, size and bytes (the digest its files
record) at another path or time is the same scan: its frame is recorded again ("source moved",
"source touched"), not done again. A skipped frame's report carries the counts stored with it, so a
summary adds up to what is on disk.
"""

from __future__ import annotations

import json
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path

from stages import load, write
from stages.errors import InputError

from .summary import FrameReport


@dataclass(frozen=True)
class Decision:
    """What to do with one frame: "do", "skip" or "replace", why it is replaced, and the metadata its
    stored Parquet records (read once: a rerun of a large dataset decides on every frame)."""

    action: str
    reason: str | None = None
    stored: dict[str, str] = field(default_factory=dict)


def stored_metadata(paths: dict[str, Path]) -> dict[str, str]:
    """The record of a frame's stored files, whatever their formats (`stages.write.stored_record`;
    {} when there is none)."""
    return write.stored_record(paths)


#: Why a finished frame is recorded again whose scan has the same bytes as the one it was made from,
#: at another path (a dataset moved or copied elsewhere) or with another modification time.
MOVED_REASONS = ("source moved", "source touched")


def decide(paths: dict[str, Path], config_hash: str, model_checksum: str, overwrite: bool,
           fingerprint: str | None = None, also_configs: tuple[str, ...] = (),
           metadata: Callable[[], Mapping[str, str] | None] | None = None,
           content: Callable[[], str] | None = None) -> Decision:
    """Skip, replace or do a frame whose outputs would be `paths` (see the module docstring).

    Args:
        fingerprint: the scan's `FrameRef.fingerprint`; None skips the source check (a frame the
            run itself just wrote).
        also_configs: other hashes of the same configuration that stored frames may carry (the
            hashes of earlier versions: `PipelineConfig.output_hash(legacy=True)`, of the weights
            as the user gave them and as resolved).
        metadata: returns the frame's timestamp and pose now, as `stages.write.metadata_record`
            gives them, or None when they cannot be read (the frame is then judged without them);
            called only for a frame that would otherwise be skipped. None: no metadata check.
        content: returns the `stages.discovery.content_digest` of the scan now; called only when
            the fingerprint differs. With it, files whose scan has the same name, size and bytes
            (`same_scan_elsewhere`) and this run's configuration and model are "replace"d with a
            `MOVED_REASONS` reason (their points stand, `pipeline.export` records them again);
            without it, or for files that record no digest (before 2026-11-27), "source changed".
    """
    if overwrite or not write.is_complete(paths):
        return Decision("do")
    # every format's file is checked (each read once): a kill between two formats' renames, or a
    # file copied in, can leave one format of another run than the others
    records = [write.stored_record({name: path}) for name, path in paths.items()]
    stored = next((record for record in records if record), {})  # as `stored_metadata` picks it
    moved = None
    for record in records:
        if fingerprint is not None and write.fingerprint_differs(record.get(write.SOURCE_KEY), fingerprint):
            moved = same_scan_elsewhere(record, fingerprint, content)
            if moved is None:
                return Decision("replace", "source changed", stored)
        # a file that records no configuration or model (written without them, e.g. by a library
        # call) cannot be shown to match: it is replaced, never trusted
        if "config_hash" not in record:
            return Decision("replace", "config not recorded", stored)
        if record["config_hash"] not in (config_hash, *also_configs):
            return Decision("replace", "config changed", stored)
        if "model_checksum" not in record:
            return Decision("replace", "model not recorded", stored)
        if record["model_checksum"] != model_checksum:
            return Decision("replace", "model changed", stored)
    if moved is not None:  # recorded again with what the dataset gives now, timestamp and pose included
        return Decision("replace", moved, stored)
    current = metadata() if metadata is not None else None
    if current is not None:
        for record in records:
            changed = write.metadata_change(record, current)
            if changed:
                return Decision("replace", changed, stored)
    return Decision("skip", stored=stored)


def same_scan_elsewhere(record: Mapping[str, str], fingerprint: str, content: Callable[[], str] | None) -> str | None:
    """"source moved" (another resolved path) or "source touched" (the same path, another
    modification time) when a stored `record` and a scan's current `fingerprint` name a file of the
    same name and size whose bytes have the digest the record holds (`content()`); None otherwise
    (another scan: the frame is done again). The name must match: the KITTI mirror names its scans
    after the input's, and a frame's number comes from it."""
    digest = record.get(write.SOURCE_DIGEST_KEY)
    if content is None or not digest or not record.get(write.SOURCE_KEY) or not fingerprint:
        return None  # a scan that cannot be stat'ed now (a broken link) has no fingerprint: its load fails
    try:
        stored, now = json.loads(record[write.SOURCE_KEY]), json.loads(fingerprint)
    except ValueError:  # a record damaged or written by another tool
        return None
    if stored.get("size") != now.get("size") or Path(stored.get("path", "")).name != Path(now.get("path", "")).name:
        return None
    if content() != digest:
        return None
    return "source moved" if stored.get("path") != now.get("path") else "source touched"


def current_metadata(ref: load.FrameRef) -> Mapping[str, str] | None:
    """`metadata_now(ref)`'s record alone."""
    return metadata_now(ref)[0]


def metadata_now(ref: load.FrameRef) -> tuple[Mapping[str, str] | None, str | None]:
    """`ref`'s timestamp and pose as the dataset gives them now (`stages.load.frame_metadata`), in
    the form its files record them, and why a part of them cannot be read (the error or note
    naming the file; None when all reads).

    The record has no "pose" when a pose file or packet the frame needs cannot be read
    (`write.metadata_change` then compares the timestamp alone: a damaged line is not a new
    pose); it is None when the timestamp cannot be read (running the frame would report why), and
    (None, None) for a plain .bin folder, which has neither."""
    if ref.dataset not in ("raw", "odometry"):
        return None, None
    try:
        timestamp, pose, note = load.frame_metadata_noted(ref)
    except (InputError, OSError, ValueError, KeyError, IndexError) as error:  # ended the whole rerun in planning, before
        return None, str(error) or type(error).__name__
    record = write.metadata_record(timestamp, pose)
    if pose is None and note:  # there, but not readable: unknown now, not changed
        del record["pose"]
    return record, note if pose is None else None


def skipped_report(ref: load.FrameRef, paths: dict[str, Path], stored: dict[str, str] | None = None) -> FrameReport:
    """The report of a frame already complete on disk, with the counts stored in its files' record
    (`stored`: that record when already read; counts a file of an earlier version lacks are 0)."""
    stored = stored if stored is not None else stored_metadata(paths)
    return FrameReport(key=ref.key, dataset=ref.dataset, sequence=ref.sequence, index=ref.index,
                       status="skipped", source=str(ref.source),
                       points_in=int(stored.get("input_points", 0)), points_out=int(stored.get("points", 0)),
                       generated=int(stored.get("generated_points", 0)), ground=int(stored.get("ground_points", 0)),
                       ground_filled=int(stored.get("ground_filled_points", 0)),
                       dropped=int(stored.get("dropped_points", 0)),
                       outputs={name: str(path) for name, path in paths.items()})


def complete_on_disk(paths: dict[str, Path], config_hash: str, model_checksum: str) -> bool:
    """True when the frame's outputs are complete and were made with this configuration and model
    (e.g. written by a worker whose report the cluster then lost)."""
    return decide(paths, config_hash, model_checksum, overwrite=False).action == "skip"
