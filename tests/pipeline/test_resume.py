"""What a re-run does with a frame already on disk (pipeline.resume): skip only what provably matches."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
import pyarrow.parquet as pq

from pipeline.chain import Chain, report, tool_version
from pipeline.config import load_config
from pipeline.resume import decide
from stages import load, write


def _library_frame(tmp_path: Path) -> tuple[dict[str, Path], str]:
    """A frame written by the library path (`Chain().run`), as a user's script writes it: its
    output paths and the configuration's hash."""
    rng = np.random.default_rng(0)
    scan = tmp_path / "scans" / "000000.bin"
    scan.parent.mkdir()
    np.column_stack([rng.normal(size=(600, 3)) * [10, 10, 1], rng.uniform(size=600)]).astype(np.float32).tofile(scan)
    config = load_config(overrides={"output.dir": str(tmp_path / "out"), "output.formats": ["parquet"]})
    frame = Chain(config).run(load.discover(scan.parent, kind="bin")[0])
    return {name: Path(path) for name, path in report(frame).outputs.items()}, config.output_hash()


def _rewrite_record(path: Path, record: dict[str, str]) -> None:
    """Replace the key-value metadata of a frame's Parquet file with `record`."""
    table = pq.read_table(path)
    pq.write_table(table.replace_schema_metadata(record), path)


def test_a_library_written_frame_records_its_config_and_model(tmp_path: Path) -> None:
    from cadpu.weights import resolve, sha256_of

    paths, config_hash = _library_frame(tmp_path)
    record = write.stored_record(paths)
    assert record["config_hash"] == config_hash
    assert record["model_checksum"] == sha256_of(resolve(load_config().upsample.weights))
    # and where the model and the tool came from, as a run's files do (`kitti-pu info` reads both)
    assert record["model_weights"] == str(resolve(load_config().upsample.weights).resolve())
    assert record["tool_version"] == tool_version()
    # so a run with other weights replaces it, and one with the same settings skips it
    assert decide(paths, config_hash, "0" * 64, overwrite=False).action == "replace"
    assert decide(paths, config_hash, record["model_checksum"], overwrite=False).action == "skip"


def test_a_frame_that_records_no_config_or_model_is_replaced_not_skipped(tmp_path: Path) -> None:
    # written by another tool or an earlier library call: nothing shows that it matches this run
    paths, config_hash = _library_frame(tmp_path)
    record = write.stored_record(paths)
    for missing, reason in (("config_hash", "config not recorded"), ("model_checksum", "model not recorded")):
        _rewrite_record(paths["parquet"], {key: value for key, value in record.items() if key != missing})
        decision = decide(paths, config_hash, record["model_checksum"], overwrite=False)
        assert (decision.action, decision.reason) == ("replace", reason)


def test_metadata_that_cannot_be_read_leaves_the_frame_judged_without_it(monkeypatch: pytest.MonkeyPatch) -> None:
    # a packet that could not be read (PermissionError) ended the whole rerun while it planned
    from pipeline.resume import current_metadata

    ref = load.FrameRef(dataset="raw", sequence="2011_09_26_drive_0001_sync", index=1, source="/x/0000000001.bin")
    for error in (PermissionError(13, "Permission denied"), np.linalg.LinAlgError("singular"), KeyError("Tr")):
        def fail(_: load.FrameRef, error: Exception = error) -> None:
            raise error
        monkeypatch.setattr(load, "frame_metadata", fail)
        assert current_metadata(ref) is None


def test_a_scan_of_the_same_name_size_and_bytes_elsewhere_is_the_same_scan(tmp_path: Path) -> None:
    from stages.discovery import content_digest

    paths, config_hash = _library_frame(tmp_path)
    record = write.stored_record(paths)
    scan = tmp_path / "scans" / "000000.bin"
    assert record[write.SOURCE_DIGEST_KEY] == content_digest(scan)  # the bytes load read
    checksum = record["model_checksum"]
    moved = tmp_path / "moved" / "000000.bin"
    moved.parent.mkdir()
    moved.write_bytes(scan.read_bytes())

    def judged(path: Path, content: bool = True) -> tuple[str, str | None]:
        decision = decide(paths, config_hash, checksum, False, load.source_fingerprint(path),
                          content=(lambda: content_digest(path)) if content else None)
        return decision.action, decision.reason

    assert judged(scan) == ("skip", None)
    assert judged(moved) == ("replace", "source moved")
    # a scan that cannot be stat'ed (a broken link) has no fingerprint: a JSONDecodeError ended the run
    broken = decide(paths, config_hash, checksum, False, "", content=lambda: "")
    assert (broken.action, broken.reason) == ("replace", "source changed")
    assert judged(moved, content=False) == ("replace", "source changed")  # not asked to read it
    renamed = tmp_path / "moved" / "000001.bin"  # another name: the mirror's file, the frame's number
    renamed.write_bytes(scan.read_bytes())
    assert judged(renamed) == ("replace", "source changed")
    edited = np.fromfile(moved, np.float32)
    edited[3] += np.float32(0.25)  # the same size, other bytes
    edited.tofile(moved)
    assert judged(moved) == ("replace", "source changed")
    # another configuration wins over a moved scan: the network runs
    moved.write_bytes(scan.read_bytes())
    decision = decide(paths, "f" * 16, checksum, False, load.source_fingerprint(moved),
                      content=lambda: content_digest(moved))
    assert (decision.action, decision.reason) == ("replace", "config changed")
