"""A frame's written output read back as the cloud it was written from, from any format.

Every output format holds the whole cloud: Parquet and PLY hold x, y, z, reflectance, generated,
ground and parent as columns; the KITTI mirror holds x, y, z and reflectance in its `.bin` and
the rest in its sidecar (`stages.write_kitti`). So a frame written in one format can be written
in another without running the network again (`pipeline.export`).
"""

from __future__ import annotations

import zipfile
import zlib
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq
from pyarrow import ArrowException

from . import write_kitti
from .frame import StitchedCloud
from .ply_format import PLY_PROPERTIES, header_vertex_count, ply_header

#: The cloud's columns, as the Parquet and PLY files name them.
CLOUD_COLUMNS = ("x", "y", "z", "reflectance", "generated", "ground", "parent")


def _columns(name: str, path: Path) -> dict[str, np.ndarray]:
    """The columns of `read_cloud` as the file of format `name` holds them."""
    if name == "parquet":
        table = pq.read_table(path, columns=list(CLOUD_COLUMNS), page_checksum_verification=True)
        return {column: table.column(column).to_numpy() for column in CLOUD_COLUMNS}
    if name == "ply":
        return _ply_columns(path)
    if name == "kitti":
        rows = np.fromfile(path, dtype=np.float32)
        if rows.size % 4:
            raise ValueError(f"{path}: not a whole number of KITTI points (x, y, z, reflectance float32)")
        rows = rows.reshape(-1, 4)
        with np.load(write_kitti.sidecar_path(path)) as sidecar:
            return {"x": rows[:, 0], "y": rows[:, 1], "z": rows[:, 2], "reflectance": rows[:, 3],
                    **{column: sidecar[column] for column in ("generated", "ground", "parent")}}
    raise ValueError(f"{path}: unknown output format {name!r}")


def read_cloud(name: str, path: Path) -> StitchedCloud:
    """The cloud a frame's file in format `name` ("parquet", "ply" or "kitti") holds; its parent
    column is what the file holds, the row in the scan (`stages.write.with_scan_rows`).

    Raises:
        ValueError naming the file when it lacks a column or is not a whole file of its format;
        OSError when it cannot be read.
    """
    path = Path(path)
    try:
        columns = _columns(name, path)
    except (ArrowException, zipfile.BadZipFile, KeyError, EOFError, zlib.error) as error:  # as the docstring says: ValueError
        raise ValueError(f"{path}: not a whole {name} file of kitti-pu ({type(error).__name__}: {error})") from None
    lengths = {len(values) for values in columns.values()}
    if len(lengths) != 1:
        raise ValueError(f"{path}: its columns differ in length ({sorted(lengths)})")
    return StitchedCloud(
        xyz=np.stack([columns["x"], columns["y"], columns["z"]], axis=1).astype(np.float32),
        reflectance=np.asarray(columns["reflectance"], dtype=np.float32),
        generated=np.asarray(columns["generated"]).astype(bool),
        ground=np.asarray(columns["ground"]).astype(bool),
        parent=np.asarray(columns["parent"], dtype=np.int64))


def _ply_columns(path: Path) -> dict[str, np.ndarray]:
    """The vertex columns of a PLY file as `stages.write.write_ply` writes it (binary little-endian,
    `PLY_PROPERTIES`)."""
    header = ply_header(path)
    if header is None:
        raise ValueError(f"{path}: no PLY header")
    body, lines = header
    properties = [tuple(line.split()[1:]) for line in lines if line.startswith("property ")]
    expected = [(kind, name) for name, kind, _ in PLY_PROPERTIES]
    if "format binary_little_endian 1.0" not in lines or properties != expected:
        raise ValueError(f"{path}: not a PLY file as kitti-pu writes them (binary little-endian, "
                         f"properties {', '.join(name for name, _, _ in PLY_PROPERTIES)})")
    dtype = np.dtype([(name, kind) for name, _, kind in PLY_PROPERTIES])
    count = header_vertex_count(lines)
    vertices = np.fromfile(path, dtype=dtype, count=count, offset=body)
    if len(vertices) != count:
        raise ValueError(f"{path}: {len(vertices)} of the {count} vertices its header announces")
    return {column: vertices[column] for column in CLOUD_COLUMNS}
