"""`kitti-pu info OUT`: what an output folder holds, read from its files alone.

Frames and points per sequence and in total come from the Parquet footers, or for a folder
without Parquet from the PLY headers or the KITTI sidecars (no point data is read); each
sequence lists the configurations (config hash) and models (checksum) that made its frames, so a
folder written by several settings shows it; the model of each checksum is named from the shipped
weights' checksums, with the patch samples it was trained on (`cadpu.train.samples_seen`); the
last run's result and per-stage timing medians come from `OUT/summary.json`.
"""

from __future__ import annotations

import json
import zipfile
import zlib
from collections import Counter
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq

from stages import write, write_kitti
from stages.discovery import content_digest, source_fingerprint
from stages.errors import first_line
from stages.ply_format import ply_is_complete, ply_vertex_count
from stages.stored import read_cloud
from stages.wording import counted

from .config import ConfigError, PipelineConfig, absolute
from .output_lock import output_busy
from .run_marks import RUNS_DIR, describe_runs, unfinished_runs


def parquet_files(out_dir: Path) -> list[Path]:
    """Every frame's Parquet file under `out_dir/points`, sorted by path: as pyarrow and pandas read
    the folder, names under `points/` starting with "." or "_" (temporaries, metadata) are not frames."""
    return _visible(Path(out_dir) / "points", "**/*.parquet")


def legacy_points_folders(out_dir: Path) -> list[Path]:
    """Folders of the earlier `points/dataset=.../sequence=...` layout under `out_dir`: readers of
    `OUT/points` would read their frames beside the current ones."""
    return sorted(Path(out_dir).glob("points/dataset=*"))


def _footer(path: Path) -> tuple[int, dict[str, str]]:
    footer = pq.read_metadata(path)
    meta = {k.decode(): v.decode() for k, v in (footer.metadata or {}).items() if not k.startswith(b"ARROW")}
    return footer.num_rows, meta


def _visible(root: Path, pattern: str) -> list[Path]:
    """The files under `root` matching `pattern`, none under a name starting with "." or "_"."""
    return sorted(path for path in root.glob(pattern)
                  if not any(part.startswith((".", "_")) for part in path.relative_to(root).parts))


def frame_records(out_dir: Path, unreadable: list[str] | None = None
                  ) -> tuple[str | None, list[tuple[int, dict[str, str]]]]:
    """Each frame's point count and record (`stages.write.frame_record`), one per frame whatever
    formats hold it: from its Parquet footer when it has a Parquet file, else its PLY header, else
    its KITTI sidecar. A Parquet file whose footer cannot be read is left out, and named in
    `unreadable` (with why) when a list is given, and so is a sidecar that does not read. Returns
    (the formats the frames were read from, joined by "+", or None when there are no frames; the
    (points, record) pairs)."""
    out_dir = Path(out_dir)
    by_format: dict[str, list[tuple[int, dict[str, str], Path]]] = {"parquet": [], "ply": [], "kitti": []}
    for path in parquet_files(out_dir):
        try:
            by_format["parquet"].append((*_footer(path), path))
        except (OSError, pa.ArrowException, UnicodeDecodeError) as error:  # truncated, or not Parquet
            if unreadable is not None:
                unreadable.append(f"{path} ({first_line(error)})")
    in_parquet = {_frame_key(record, path) for _, record, path in by_format["parquet"]}
    for path in _visible(out_dir / "ply", "**/*.ply"):
        if path.stem.isdigit() and (path.parent.parent.name, path.parent.name, str(int(path.stem))) in in_parquet:
            continue  # the frame counts by its Parquet file: its PLY header is not read
        record = write.stored_record({"ply": path})
        by_format["ply"].append((int(record["points"]) if "points" in record else ply_vertex_count(path), record, path))
    for path in _visible(out_dir / "kitti", "**/*.npz"):
        if path.parent.name != write_kitti.SIDECAR_FOLDER:
            continue
        try:
            record, rows = write_kitti.sidecar_record(path)
        except (OSError, ValueError, KeyError, zipfile.BadZipFile) as error:  # damaged: not a frame, but said
            if unreadable is not None:
                unreadable.append(f"{path} ({first_line(error)})")
            continue
        by_format["kitti"].append((int(record.get("points", rows)), record, path))
    frames: dict[tuple[str, ...], tuple[int, dict[str, str]]] = {}
    read_from = []
    for name, found in by_format.items():  # Parquet first: a frame's first format is what it counts by
        added = 0
        for rows, record, path in found:
            key = _frame_key(record, path)
            if key not in frames:
                frames[key] = (rows, record)
                added += 1
        if added:
            read_from.append(name)
    return ("+".join(read_from) or None), list(frames.values())


def _frame_key(record: dict[str, str], path: Path) -> tuple[str, ...]:
    """Which frame a stored file holds: (dataset, sequence, frame number) from its record, or its
    path when the record lacks them."""
    if {"dataset", "sequence", "frame"} <= record.keys():
        return record["dataset"], record["sequence"], record["frame"]
    return (str(path),)


def frame_files(out_dir: Path) -> list[tuple[str, Path]]:
    """Every frame file of `out_dir` as (format, path): its Parquet files, its PLY files, and the
    scans of its KITTI mirror that have a sidecar (those the tool wrote)."""
    out_dir = Path(out_dir)
    # the mirror keeps a scan's own name, .BIN too
    mirror = [path for path in _mirror_scans(out_dir) if write_kitti.sidecar_path(path).is_file()]
    return ([("parquet", path) for path in parquet_files(out_dir)]
            + [("ply", path) for path in _visible(out_dir / "ply", "**/*.ply")] + [("kitti", path) for path in mirror])


def _mirror_scans(out_dir: Path) -> list[Path]:
    """The `.bin` scans of `out_dir`'s KITTI mirror (the mirror keeps a scan's own name, .BIN too)."""
    return [path for path in _visible(Path(out_dir) / "kitti", "**/*")
            if path.suffix.lower() == ".bin" and path.is_file()]


def unpaired_mirror_files(out_dir: Path) -> list[str]:
    """The KITTI mirror's scans without their sidecar and sidecars without their scan, each with
    why: the tool writes the two together, so either alone is a frame copy that lost a file (a
    KITTI reader reads such a scan as a frame, but `preview` refuses it and a run writes it again)."""
    sidecars = {scan: write_kitti.sidecar_path(scan) for scan in _mirror_scans(out_dir)}
    paired = set(sidecars.values())
    lone_scans = [f"{scan} (a scan of the KITTI copy without its sidecar {sidecar.name} in "
                  f"{write_kitti.SIDECAR_FOLDER}/: not a whole kitti-pu frame; kitti-pu run writes it again)"
                  for scan, sidecar in sidecars.items() if not sidecar.is_file()]
    lone_sidecars = [f"{sidecar} (a sidecar of the KITTI copy without its scan: kitti-pu run writes the frame again)"
                     for sidecar in _visible(Path(out_dir) / "kitti", f"**/{write_kitti.SIDECAR_FOLDER}/*.npz")
                     if sidecar not in paired]
    return lone_scans + lone_sidecars


def damaged_frame_files(out_dir: Path) -> list[str]:
    """Every frame file of `out_dir`, in every format, read whole (`kitti-pu info --verify`): the
    files whose data cannot be read (a Parquet page that does not decompress or does not match its
    CRC-32, a PLY of another size than its header says, a KITTI scan of another point count than
    its sidecar, a sidecar member that does not read), that hold a non-finite value, or that
    disagree with the record they hold (`record_disagreement`), the KITTI copy's scans and
    sidecars each without the other (`unpaired_mirror_files`), and the files of a frame whose
    formats disagree with each other (`formats_disagree`), each with why. A run's skip check
    reads only a file's footer or header, so damage inside a file written whole (a disk error, a
    bad copy) shows only here, or to a reader."""
    damaged = []
    formats_of_frame: dict[tuple[str | None, ...], list[tuple[str, Path, dict[str, str]]]] = {}
    for name, path in frame_files(Path(out_dir)):
        if name == "kitti":  # a damaged sidecar is named itself, not the scan beside it
            sidecar = write_kitti.sidecar_path(path)
            try:
                write_kitti.sidecar_record(sidecar)
                with np.load(sidecar) as arrays:  # every member against its zip CRC, not only the record's
                    for member in arrays.files:
                        arrays[member]
            except (OSError, ValueError, KeyError, EOFError, zipfile.BadZipFile, zlib.error) as error:
                damaged.append(f"{sidecar} (the sidecar of {path.name}: {first_line(error)})")
                continue
        try:
            if name == "ply" and not ply_is_complete(path):
                raise ValueError("not the size its header announces")
            if name == "kitti" and not write_kitti.is_complete(path):
                labels = write_kitti.labels_out_of_step(path)
                if labels is not None:  # the labels named, not the scan beside them (a trial)
                    damaged.append(f"{labels} (not one label for each point of {path.name})")
                    continue
                raise ValueError("not the whole number of points its sidecar holds")
            cloud = read_cloud(name, path)  # every column, each Parquet page against its CRC-32
            if not (np.isfinite(cloud.xyz).all() and np.isfinite(cloud.reflectance).all()):
                damaged.append(f"{path} (a non-finite value)")
            elif (disagreement := record_disagreement(name, path, len(cloud),
                                                      record := write.stored_record({name: path}))) is not None:
                damaged.append(f"{path} ({disagreement})")
            else:
                key = (record.get("dataset"), record.get("sequence"), record.get("frame"))
                formats_of_frame.setdefault(key, []).append((name, path, record))
        except (OSError, ValueError, pa.ArrowException, UnicodeDecodeError, KeyError, zipfile.BadZipFile,
                zlib.error) as error:
            damaged.append(f"{path} ({first_line(error)})")
    return (damaged + unpaired_mirror_files(Path(out_dir))
            + [described for files in formats_of_frame.values() if (described := formats_disagree(files))])


def formats_disagree(files: list[tuple[str, Path, dict[str, str]]]) -> str | None:
    """Why one frame's files in several formats (format, path, record) are not of one run's
    making, or None: a file whose configuration, model, scan, timestamp or pose differs from the
    first file's (Parquet's when there is one), compared as a run compares them
    (`write.fingerprint_differs`, `write.metadata_change`). A run killed while it replaced the frame
    left its other formats' files of before (`pipeline.run_marks`), and readers of those get the
    old frame. Configuration hashes are compared only between records that also hold the settings
    (`write.CONFIG_KEY`): an earlier version's hash of the same settings is one a run still takes."""
    reference_name, reference_path, reference = files[0]
    for _, path, record in files[1:]:
        settings_known = write.CONFIG_KEY in record and write.CONFIG_KEY in reference
        differs = ("configuration" if settings_known and record.get("config_hash") != reference.get("config_hash") else
                   "model" if "model_checksum" in record and "model_checksum" in reference
                   and record["model_checksum"] != reference["model_checksum"] else
                   "scan" if write.SOURCE_KEY in record and write.SOURCE_KEY in reference
                   and _fingerprints_differ(record[write.SOURCE_KEY], reference[write.SOURCE_KEY]) else
                   (write.metadata_change(record, reference) or "").removesuffix(" changed") or None)
        if differs:
            return (f"{path} (records another {differs} than its {reference_name} file {reference_path.name}: "
                    "remove the one not wanted, or run again writing both formats)")
    return None


def _fingerprints_differ(stored: str, other: str) -> bool:
    """`write.fingerprint_differs` between two records' fingerprints: the same text (an empty one
    too, a frame written without its scan) is the same scan; one edited by hand (not JSON) differs."""
    if stored == other:
        return False
    try:
        return write.fingerprint_differs(stored, other)
    except ValueError:
        return True


#: The Parquet columns that hold one value a frame, the frame's record's key for each.
FRAME_NAME_COLUMNS = {"frame": "frame", "dataset": "dataset", "sequence": "sequence"}


def record_disagreement(name: str, path: Path, points: int, record: dict[str, str] | None = None) -> str | None:
    """What in a frame file that reads whole disagrees with the record it holds (`--verify`), or
    None: the record's point count against the `points` rows the file holds, and in a Parquet file
    the frame, dataset and sequence columns (read whole, each page against its CRC-32) and their
    footer statistics, which readers filter frames by, against the record's frame name. The
    footer holds no checksum; these are what a changed byte in it changes that readers act on.
    `record`: the file's record when the caller has read it."""
    record = write.stored_record({name: path}) if record is None else record
    if record.get("points", str(points)) != str(points):
        return f"its record says {record['points']} points, it holds {points}"
    if name != "parquet" or not all(key in record for key in FRAME_NAME_COLUMNS.values()):
        return None
    expected = {"frame": int(record["frame"]), "dataset": record["dataset"], "sequence": record["sequence"]}
    parquet = pq.ParquetFile(path, page_checksum_verification=True)  # its footer read once, for all below
    # files of the earlier points/dataset=.../sequence=... layout hold the frame column only
    held_columns = [column for column in FRAME_NAME_COLUMNS if column in parquet.schema_arrow.names]
    table = parquet.read(columns=held_columns)
    for column in held_columns:
        held = set(pc.unique(table.column(column)).to_pylist())  # a few values: no Python object a row
        if held - {expected[column]}:
            return f"its {column} column holds {sorted(map(str, held))[:3]}, its record {expected[column]!r}"
    footer = parquet.metadata
    for group in range(footer.num_row_groups):
        chunks = footer.row_group(group)
        for index in range(chunks.num_columns):
            chunk = chunks.column(index)
            statistics = chunk.statistics
            column = chunk.path_in_schema
            if column in FRAME_NAME_COLUMNS and statistics is not None and statistics.has_min_max and (
                    statistics.min != expected[column] or statistics.max != expected[column]):
                return (f"the footer's statistics of its {column} column say {statistics.min!r} to "
                        f"{statistics.max!r}, its rows {expected[column]!r}: readers that filter by them miss rows")
    return None


def describe_model(checksum: str, weights_file: str | None = None) -> dict[str, Any]:
    """The model of a weights checksum: {"checksum", "name", "samples_seen", "finetuned_from",
    "finetune_scans"}. The name is that of the shipped weights file with this sha256, else
    `weights_file` (the file the frames record they were made with) when it is still there with
    this sha256, else None; samples_seen the patch samples that file was trained on, finetuned_from
    the file it was fine-tuned from (`kitti-pu finetune`) and finetune_scans the count of real
    scans its fine-tuning runs trained on, all of them (each None when unknown or not fine-tuned)."""
    from cadpu.weights import WEIGHTS_DIR, sha256_of

    found: Path | None = None
    for checksum_file in sorted(WEIGHTS_DIR.glob("*.pt.sha256")):
        words = checksum_file.read_text().split()
        if words and words[0] == checksum:
            found = checksum_file.with_suffix("")
            break
    if found is None and weights_file and Path(weights_file).is_file() and sha256_of(Path(weights_file)) == checksum:
        found = Path(weights_file)
    if found is None:
        return {"checksum": checksum, "name": None, "samples_seen": None, "finetuned_from": None, "finetune_scans": None}
    from cadpu.train import samples_seen

    meta = _weights_meta(found)
    return {"checksum": checksum, "name": found.stem if found.parent == WEIGHTS_DIR else weights_file,
            "samples_seen": None if meta is None else samples_seen(meta),
            "finetuned_from": ((meta or {}).get("finetuned_from") or {}).get("weights"),
            "finetune_scans": len(meta["finetune_scans"]) if meta and "finetune_scans" in meta else None}


def _weights_meta(weights: Path) -> dict[str, Any] | None:
    """A weights file's meta dict, None when the file does not read (its name is still worth printing)."""
    import torch

    try:
        meta = torch.load(weights, map_location="cpu", weights_only=True).get("meta", {})
    except Exception:  # noqa: BLE001 (any file that does not read: its name is still worth printing)
        return None
    return meta if isinstance(meta, dict) else None


#: What `format_info` reads of summary.json besides its frames.
LAST_RUN_KEYS = ("frames_done", "frames_skipped", "frames_failed", "frames_total", "wall_seconds", "exit_code",
                 "ratio", "model_checksum")


def _latest_timings(out_dir: Path) -> tuple[dict[str, float], str | None]:
    """The per-stage medians of the latest run recorded in `OUT/runs/` that did frames, and that
    record's name; ({}, None) when none did (or none is readable)."""
    for record in sorted((Path(out_dir) / RUNS_DIR).glob("*.json"), reverse=True):  # named by UTC time
        try:
            medians = json.loads(record.read_text()).get("stage_median_ms") or {}
        except (OSError, ValueError, AttributeError):
            continue
        if medians:
            return medians, record.name
    return {}, None


def _newest_record(out_dir: Path) -> Path | None:
    """The newest run record in `OUT/runs/` (named by UTC time), or None."""
    records = sorted((Path(out_dir) / RUNS_DIR).glob("*.json"))
    return records[-1] if records else None


def _newer(path: Path, than: Path) -> bool:
    """Whether the file `path` exists and was modified after `than` (a later run's summary.json
    than a record whose run could not write its own)."""
    try:
        return path.stat().st_mtime_ns > than.stat().st_mtime_ns
    except OSError:
        return False


def _summary_missing(record: Path) -> bool:
    """Whether the run of `record` could not write its summary.json (the record says why)."""
    try:
        return bool(json.loads(record.read_text()).get("summary_missing"))
    except (OSError, ValueError, AttributeError):
        return False


def folder_info(out_dir: Path) -> dict[str, Any]:
    """What `out_dir` holds, as a JSON-ready dict (what `kitti-pu info --json` prints).

    Keys: output_dir; read_from (the format whose files were read: `frame_records`); frames,
    points, generated (totals); sequences (one dict per dataset and
    sequence: frames, points, generated, configs {config hash: frames}, models {checksum:
    frames}); models (`describe_model` of each checksum found); mixed (True when some sequence
    was made by more than one configuration or model); legacy_folders; last_run (summary.json's
    totals and stage_median_ms, or those of the newest record in OUT/runs/ when its run could not
    write summary.json (its summary_missing says why), or None; when that run did no frame, the
    medians of the latest run in OUT/runs/ that did, named by timings_from); unreadable (files left out: path and why);
    sources_missing (the source scans of frames here that this machine cannot find: deleted or
    moved since, or on another machine); sources_changed (the source scans that are there but
    changed since: size, modification time or resolved path); scans_twice ({scan: its frames} for
    scans held as more than one frame); run_in_progress (whether a run holds the folder's lock
    now); unfinished_runs (`pipeline.run_marks.unfinished_runs`: runs that never finished). Each sequence also counts its frames by input_folders (the folders their
    scans were read from; more than one when another dataset's sequence of the same name was run
    into the folder).

    Raises ConfigError when `out_dir` holds no kitti-pu output (a run's mark alone counts as output).
    """
    out_dir = Path(out_dir)
    if not out_dir.is_dir():
        raise ConfigError(f"info: {out_dir} {'is not a folder' if out_dir.exists() else 'does not exist'}; "
                          "give a run's output folder (kitti-pu run --out)")
    if out_dir.name in write.DATA_FOLDERS.values() and (out_dir.parent / "summary.json").is_file():
        raise ConfigError(f"info: {out_dir} is a data folder of the output {out_dir.parent}; give that folder")
    unreadable: list[str] = []
    read_from, records = frame_records(out_dir, unreadable)
    summary_path = out_dir / "summary.json"
    marks = unfinished_runs(out_dir)
    # a run killed before its first frame leaves only its mark: that is worth saying, not "no output"
    if not records and not summary_path.is_file() and not marks:
        if unreadable:
            raise ConfigError(f"info: {out_dir} holds no readable kitti-pu frame; unreadable: {'; '.join(unreadable)}")
        raise ConfigError(f"info: {out_dir} holds no kitti-pu output (no frames in points/, ply/ or kitti/, "
                          "no summary.json)")
    sequences: dict[tuple[str, str], dict[str, Any]] = {}
    frames_of_scan: dict[str, list[str]] = {}
    settings: dict[str, str] = {}  # config hash -> the settings it stands for, as the files record them
    for rows, meta in records:
        key = (meta.get("dataset", "?"), meta.get("sequence", "?"))
        entry = sequences.setdefault(key, {"dataset": key[0], "sequence": key[1], "frames": 0, "points": 0,
                                           "generated": 0, "configs": Counter(), "models": Counter(),
                                           "input_folders": Counter()})
        entry["frames"] += 1
        entry["points"] += rows
        entry["generated"] += int(meta.get("generated_points", 0))
        entry["configs"][meta.get("config_hash", "unknown")] += 1
        if meta.get(write.CONFIG_KEY):
            settings.setdefault(meta.get("config_hash", "unknown"), meta[write.CONFIG_KEY])
        entry["models"][meta.get("model_checksum", "unknown")] += 1
        # the path as discovered, not resolved: scans linked to one file (a deduplicated dataset)
        # are separate frames of their own names
        scan = meta.get("source", "")
        if scan:
            entry["input_folders"][str(Path(scan).parent)] += 1
            frame = meta.get("frame", "?")
            frames_of_scan.setdefault(scan, []).append(f"{key[0]}/{key[1]}/{int(frame):06d}" if frame.isdigit()
                                                       else f"{key[0]}/{key[1]}/{frame}")
    listed = [{**entry, "configs": dict(entry["configs"]), "models": dict(entry["models"]),
               "input_folders": dict(entry["input_folders"])} for _, entry in sorted(sequences.items())]
    # one scan written as several frames: named two ways (an odometry sequence, and its velodyne/
    # folder as plain .bin files), so a reader of the folder reads its points twice
    scans_twice = {scan: keys for scan, keys in sorted(frames_of_scan.items()) if len(keys) > 1}
    # frames whose scan is gone (deleted, moved, or on another machine): kept, never redone
    gone = sorted(meta["source"] for _, meta in records if meta.get("source") and not Path(meta["source"]).exists())
    # frames whose scan is there but another now (edited, replaced, touched): the next run redoes them
    missing = set(gone)
    changed = sorted(meta["source"] for _, meta in records if meta.get("source") and meta["source"] not in missing
                     and _scan_changed(meta))
    busy = output_busy(out_dir)
    checksums = sorted({checksum for entry in listed for checksum in entry["models"] if checksum != "unknown"})
    files = {meta.get("model_checksum"): meta.get("model_weights") for _, meta in records if meta.get("model_weights")}
    last_run = None
    # a run whose summary.json could not be written (a full disk) says so in its record in runs/
    newest = _newest_record(out_dir)
    last_path = (newest if newest is not None and _summary_missing(newest)
                 and not _newer(summary_path, newest) else summary_path)
    if last_path.is_file():
        try:
            last = json.loads(last_path.read_text())
            last_run = {key: value for key, value in last.items() if key != "frames"}
            missing = sorted(set(LAST_RUN_KEYS) - set(last_run))
            if missing:  # another version's, or edited by hand
                raise KeyError(f"no {', '.join(missing)}")
            last_run["failed"] = [{"key": f["key"], "error": f["error"]} for f in last["frames"]
                                  if f["status"] == "failed"]
            if not last_run.get("stage_median_ms"):  # it did no frame: the timings of the last that did
                last_run["stage_median_ms"], last_run["timings_from"] = _latest_timings(out_dir)
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as error:  # half-written, edited
            unreadable.append(f"{last_path} ({type(error).__name__}: {first_line(error)})")
            last_run = None
    return {
        "output_dir": str(absolute(out_dir)),
        "read_from": read_from,
        "frames": sum(entry["frames"] for entry in listed),
        "points": sum(entry["points"] for entry in listed),
        "generated": sum(entry["generated"] for entry in listed),
        "sequences": listed,
        "models": [describe_model(checksum, files.get(checksum)) for checksum in checksums],
        "config_settings": {config_hash: _settings_changed(settings.get(config_hash))
                            for config_hash in sorted({c for entry in listed for c in entry["configs"]})},
        "mixed": any(len(entry["configs"]) > 1 or len(entry["models"]) > 1 for entry in listed)
                 or len({c for entry in listed for c in entry["configs"]}) > 1,
        "legacy_folders": [str(path) for path in legacy_points_folders(out_dir)],
        "sources_missing": gone,
        "sources_changed": changed,
        "scans_twice": scans_twice,
        "last_run": last_run,
        "unreadable": unreadable,
        "run_in_progress": busy,
        # a run's mark without a run holding the lock: one that never finished (`pipeline.run_marks`)
        "unfinished_runs": [] if busy else marks,
    }


def rewritten_sources(out_dir: Path) -> list[str]:
    """The scans of `out_dir`'s frames whose bytes are no longer those their frame was made from
    although their size and modification time are (`kitti-pu info --verify`): a scan rewritten in
    place and its time set back (`cp -p`, `rsync -a`, `touch -r`). A run's skip check compares
    path, size and time only, so it keeps such a frame; reading every scan is for --verify. Frames
    whose record holds no digest of their scan (an earlier version's) are not compared."""
    rewritten = set()
    for _, record in frame_records(Path(out_dir))[1]:
        source, digest = record.get("source", ""), record.get(write.SOURCE_DIGEST_KEY)
        if not source or not digest or not Path(source).is_file() or _scan_changed(record):
            continue  # no digest to compare, gone (sources_missing) or changed (sources_changed)
        now = content_digest(source)
        if now and now != digest:  # "": the scan cannot be read now, which is not a rewrite
            rewritten.add(source)
    return sorted(rewritten)


def stale_mirror_labels(out_dir: Path) -> list[str]:
    """The KITTI mirror's frames of `out_dir` whose SemanticKITTI labels are not the input's as it
    is now (`kitti-pu info --verify`): labels the input gained, changed or lost since the frame was
    mirrored, which a run brings up to date only for the frames it selects
    (`stages.write_kitti.labels_update_due`; a run of other frames left them stale without a word:
    a batch user's trial). Returns the mirrored scans' paths."""
    stale = []
    for name, scan in frame_files(Path(out_dir)):
        if name != "kitti":
            continue
        record = write.stored_record({name: scan})
        source = record.get("source", "")
        if (record.get("dataset") == "odometry" and source and Path(source).is_file()
                and write_kitti.labels_update_due("odometry", source, scan)):
            stale.append(str(scan))
    return stale


def _scan_changed(record: dict[str, str]) -> bool:
    """Whether the scan a frame's record names is no longer the one it was made from (its size,
    modification time or resolved path differ from the record's fingerprint); False when the
    record holds no fingerprint to compare."""
    stored = record.get(write.SOURCE_KEY)
    if not stored:
        return False
    try:
        return write.fingerprint_differs(stored, source_fingerprint(record["source"]))
    except ValueError:  # a record edited by hand: nothing to compare
        return False


def _settings_changed(recorded: str | None) -> dict[str, Any] | None:
    """The output settings a frame's record holds (`stages.write.CONFIG_KEY`) that differ from
    this version's defaults, as {"section.key": value}; None when the record holds none (written
    by an earlier version) or it does not read."""
    try:
        given = json.loads(recorded) if recorded else None
    except ValueError:
        return None
    if not isinstance(given, dict):
        return None
    defaults = _flat(PipelineConfig().output_settings())
    return {key: value for key, value in sorted(_flat(given).items()) if defaults.get(key, _ABSENT) != value}


_ABSENT = object()


def _flat(settings: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Nested settings as {"section.key": value} (an empty mapping is a value of its own)."""
    flat: dict[str, Any] = {}
    for key, value in settings.items():
        if isinstance(value, dict) and value:
            flat.update(_flat(value, f"{prefix}{key}."))
        else:
            flat[f"{prefix}{key}"] = value
    return flat


def _counts(counter: dict[str, int]) -> str:
    return ", ".join(f"{key[:16]} ({count} frame{'' if count == 1 else 's'})" for key, count in sorted(counter.items()))


def format_info(info: dict[str, Any]) -> str:
    """`folder_info`'s dict as the text `kitti-pu info` prints."""
    lines = [f"{'dataset':<10} {'sequence':<32} {'frames':>7} {'points':>12} {'generated':>12}"]
    for entry in info["sequences"]:
        lines.append(f"{entry['dataset']:<10} {entry['sequence']:<32} {entry['frames']:>7} "
                     f"{entry['points']:>12} {entry['generated']:>12}")
    lines.append(f"{'total':<43} {info['frames']:>7} {info['points']:>12} {info['generated']:>12}")
    read_from = (info.get("read_from") or "").split("+")
    if read_from != [""] and read_from != ["parquet"]:
        names = [{"parquet": "Parquet", "ply": "PLY", "kitti": "KITTI sidecar"}[name] for name in read_from]
        sources = " and ".join([", ".join(names[:-1]), names[-1]] if len(names) > 1 else names)
        lines.append(f"  (counted from the {sources} files: "
                     + ("some frames have no readable Parquet file)" if "parquet" in read_from
                        else "no Parquet files)"))
    if info["sequences"]:
        lines.append("configs (config hash) and models (weights sha256) per sequence:")
    for entry in info["sequences"]:
        lines.append(f"  {entry['dataset']}/{entry['sequence']}: config {_counts(entry['configs'])}; "
                     f"model {_counts(entry['models'])}")
    for config_hash, changed in info["config_settings"].items():
        described = ("settings not recorded (frames of an earlier version)" if changed is None else
                     "the default settings" if not changed else
                     ", ".join(f"{key}={json.dumps(value)}" for key, value in changed.items()))
        lines.append(f"  config {config_hash[:16]}: {described}")
    if info["mixed"]:
        lines.append("  note: this folder holds frames made by more than one configuration or model")
    for model in info["models"]:
        name = model["name"] or "not a shipped weights file, nor one the frames name and still there"
        samples = "unknown" if model["samples_seen"] is None else f"{model['samples_seen']:,}"
        # a fine-tuned file read as one trained on its samples alone, most of them its base's (a trial)
        scans = model.get("finetune_scans")
        tuned = ("" if not model.get("finetuned_from") else f" (fine-tuned from {model['finetuned_from']}"
                 + (f"; {counted(scans, 'real scan')} over its fine-tuning runs)" if scans else ")"))
        lines.append(f"  model {model['checksum'][:16]}: {name}, trained on {samples} patch samples{tuned}")
    last = info["last_run"]
    if last is not None:
        stopped = (f", not reached {last.get('frames_interrupted', 0)} (stopped by "
                   f"{last.get('interrupted_by') or 'a signal'})" if last.get("interrupted") else
                   f", not reached {last['frames_interrupted']}" if last.get("frames_interrupted") else "")
        if last.get("summary_missing"):
            lines.append(f"warning: the last run's summary.json could not be written ({last['summary_missing']}); "
                         "its record in runs/ says:")
        lines.append(f"last run: done {last['frames_done']}, skipped {last['frames_skipped']}, failed "
                     f"{last['frames_failed']}{stopped} of {last['frames_total']} frames in {last['wall_seconds']} s "
                     f"(exit {last['exit_code']}, ratio {last['ratio']}, model {last['model_checksum'][:12]})")
        medians = last.get("stage_median_ms") or {}
        if medians:
            which = (f"the last run that did frames ({last['timings_from']})" if last.get("timings_from")
                     else "last run")
            lines.append(f"{which}, median ms per frame: "
                         + ", ".join(f"{stage} {ms:g}" for stage, ms in medians.items()))
        for failed in last["failed"]:
            lines.append(f"  failed {failed['key']}: {failed['error']}")
    for described in info.get("unreadable", []):
        lines.append(f"warning: unreadable, left out: {described}")
    if "damaged" in info:  # --verify
        lines += [f"damaged: {described}" for described in info["damaged"]] or [
            # PLY and KITTI files hold no checksum: "verified" read as if a changed byte in them
            # would have been found (a trial)
            "verified: every frame file reads whole, in every format (Parquet pages against their "
            "checksums; PLY and KITTI files by their size only, their contents unchecked; each file's "
            "point count and frame name against its record)"]
    for entry in info["sequences"]:
        folders = entry.get("input_folders", {})
        if len(folders) > 1:
            lines.append(f"warning: {entry['dataset']} {entry['sequence']} holds frames of {len(folders)} input "
                         f"folders: " + ", ".join(f"{folder} ({count})" for folder, count in sorted(folders.items())))
    twice = info.get("scans_twice", {})
    if twice:
        scan, keys = next(iter(twice.items()))
        lines.append(f"warning: {len(twice)} scan(s) are in the folder as more than one frame, so readers get their "
                     f"points more than once, e.g. {scan} as {' and '.join(keys)}")
    if info.get("sources_missing"):
        gone = info["sources_missing"]
        lines.append(f"warning: {len(gone)} frame(s) whose scan is not found from here (deleted or moved since, or "
                     f"on another machine), e.g. {gone[0]}: their files stay until removed")
    if info.get("sources_changed"):
        changed = info["sources_changed"]
        lines.append(f"warning: {len(changed)} frame(s) whose scan has changed since they were made (its size, "
                     f"modification time or resolved path), e.g. {changed[0]}: the next run redoes them (one "
                     "whose bytes are those it was made from, moved or touched, is only recorded again)")
    if info.get("sources_rewritten"):  # --verify
        rewritten = info["sources_rewritten"]
        lines.append(f"warning: {len(rewritten)} scan(s) holding other bytes than their frames were made from, "
                     f"their size and modification time unchanged (copied over with cp -p?), e.g. {rewritten[0]}: "
                     "a run keeps their frames; touch the scans to have the next run redo them")
    if info.get("labels_stale"):  # --verify
        stale = info["labels_stale"]
        lines.append(f"warning: {len(stale)} mirrored frame(s) whose SemanticKITTI labels are not the input's as it "
                     f"is now, e.g. {stale[0]}: a run that selects those frames brings them up to date")
    if info.get("run_in_progress"):
        lines.append(f"warning: a kitti-pu run is writing to {info['output_dir']} now: these counts are of the "
                     "frames finished so far")
    if info.get("unfinished_runs"):
        lines.append(f"warning: {describe_runs(info['unfinished_runs'])} did not finish (killed?); the next run "
                     "checks the files its frames left in the formats it did not write")
    for folder in info["legacy_folders"]:
        lines.append(f"warning: {folder} is in the earlier dataset=/sequence= layout; readers of points/ "
                     "read it too: move or remove it")
    return "\n".join(lines)
