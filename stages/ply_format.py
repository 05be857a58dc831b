"""The binary PLY that `stages.write` writes: its vertex layout, its rows packed in one compiled
pass, and the check that a file holds every row its header announces.

Filling a numpy structured array field by field makes eight strided passes over the output and
then a copy of it (`tobytes`); `ply_rows` writes each row's 26 bytes once, into the buffer the
file is written from. The bytes are those of the structured array of `PLY_PROPERTIES` (tested).
"""

from __future__ import annotations

from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
from numba import njit

if TYPE_CHECKING:
    from .frame import StitchedCloud

#: PLY vertex properties: name, PLY type, numpy type (little-endian, as the header says).
PLY_PROPERTIES = (("x", "float", "<f4"), ("y", "float", "<f4"), ("z", "float", "<f4"),
                  ("reflectance", "float", "<f4"), ("generated", "uchar", "u1"), ("ground", "uchar", "u1"),
                  ("parent", "int", "<i4"), ("frame", "int", "<i4"))
#: Bytes per vertex row.
PLY_ROW_BYTES = sum(np.dtype(dtype).itemsize for _, _, dtype in PLY_PROPERTIES)


def ply_rows(cloud: "StitchedCloud", frame_index: int, out: np.ndarray) -> np.ndarray:
    """Pack the cloud's vertex rows (`PLY_PROPERTIES`, little-endian) into `out`.

    Args:
        cloud: Q points; parent ids are written as int32 (scans hold far fewer than 2**31 points).
        frame_index: the frame column's value.
        out: (Q * PLY_ROW_BYTES,) uint8, C-contiguous.

    Returns:
        `out`.
    """
    count = len(cloud)
    if out.shape != (count * PLY_ROW_BYTES,) or out.dtype != np.uint8:
        raise ValueError(f"ply_rows: need a ({count * PLY_ROW_BYTES},) uint8 buffer, got {out.dtype} {out.shape}")

    def little(values: np.ndarray, dtype: str) -> np.ndarray:
        return np.ascontiguousarray(values, dtype=dtype).view(np.uint8).reshape(-1)

    _pack(little(cloud.xyz, "<f4"), little(cloud.reflectance, "<f4"), little(cloud.generated, "u1"),
          little(cloud.ground, "u1"), little(cloud.parent, "<i4"), little(np.array([frame_index]), "<i4"), out)
    return out


@njit(cache=True, nogil=True)
def _pack(xyz: np.ndarray, reflectance: np.ndarray, generated: np.ndarray, ground: np.ndarray,
          parent: np.ndarray, frame: np.ndarray, out: np.ndarray) -> None:  # pragma: no cover - compiled
    """Interleave the columns' bytes (12, 4, 1, 1, 4 per row; frame: 4 bytes, every row) into
    26-byte rows."""
    for i in range(len(generated)):
        row = i * 26
        for b in range(12):
            out[row + b] = xyz[i * 12 + b]
        for b in range(4):
            out[row + 12 + b] = reflectance[i * 4 + b]
        out[row + 16] = generated[i]
        out[row + 17] = ground[i]
        for b in range(4):
            out[row + 18 + b] = parent[i * 4 + b]
            out[row + 22 + b] = frame[b]


#: The most a PLY header is read for (its comments hold the frame's record, with source paths).
HEADER_LIMIT = 1 << 16


def ply_header(path: Path) -> tuple[int, list[str]] | None:
    """(the body's offset, the header's lines) of a PLY file, or None when it has no PLY header
    within HEADER_LIMIT bytes."""
    with Path(path).open("rb") as handle:
        head = handle.read(HEADER_LIMIT)
    end = head.find(b"end_header\n")
    if not head.startswith(b"ply") or end < 0:
        return None
    return end + len(b"end_header\n"), head[:end].decode("ascii", "replace").splitlines()


def ply_vertex_count(path: Path) -> int:
    """The vertex count a PLY header announces (0 without a header)."""
    header = ply_header(path)
    return header_vertex_count(header[1]) if header else 0


def header_vertex_count(lines: list[str]) -> int:
    """The vertex count the lines of a PLY header announce (0 when they announce none)."""
    for line in lines:
        words = line.split()
        if words[:2] == ["element", "vertex"]:
            return int(words[2])
    return 0


def ply_is_complete(path: Path) -> bool:
    """The PLY's body has exactly the byte count its header announces (binary, fixed-size
    properties): shorter is a cut file; longer, a header whose vertex count lost rows (readers
    such as trimesh refuse it, others read fewer vertices) or bytes appended."""
    sizes = {"char": 1, "uchar": 1, "int8": 1, "uint8": 1, "short": 2, "ushort": 2, "int16": 2,
             "uint16": 2, "int": 4, "uint": 4, "int32": 4, "uint32": 4, "float": 4, "float32": 4,
             "double": 8, "float64": 8, "int64": 8, "uint64": 8}
    header = ply_header(path)
    if header is None:
        return False
    body, lines = header
    row = sum(sizes.get(words[1], 0) for words in map(str.split, lines)
              if words[:1] == ["property"] and len(words) == 3)
    return path.stat().st_size == body + ply_vertex_count(path) * row
