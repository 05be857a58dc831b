"""Compare the frames two output folders hold: per frame, the point count and a digest of the
points, and whether the files' contents are equal.

    python bench/output_digest.py OUT_A OUT_B

For every Parquet file under OUT_A/points (and its namesake under OUT_B): rows, the sha256 of the
x, y, z columns sorted by x, then y, then z (independent of point order), whether the two tables
are equal column by column, whether their key-value metadata is equal (pyarrow's stored Arrow
schema left out), and whether the two PLY files under ply/ are byte for byte equal. Where the
tables differ, the largest absolute difference of x, y, z (same row counts) is printed. Made to
check that a change in the stitch, snap, fill or write code left the output unchanged, e.g. with
`bench/stitch.py --keep OUT` run on two revisions.
"""

from __future__ import annotations

import argparse
import hashlib
from pathlib import Path

import numpy as np
import pyarrow.parquet as pq

#: Key-value metadata pyarrow adds by itself (the serialized Arrow schema), not compared.
ARROW_SCHEMA_KEY = b"ARROW:schema"


def xyz_digest(xyz: np.ndarray) -> str:
    """sha256 (hex, first 16 digits) of (N, 3) float32 points sorted by x, then y, then z."""
    ordered = np.ascontiguousarray(xyz[np.lexsort(xyz.T[::-1])], dtype=np.float32)
    return hashlib.sha256(ordered.tobytes()).hexdigest()[:16]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("first", type=Path)
    parser.add_argument("second", type=Path)
    args = parser.parse_args()
    files = sorted((args.first / "points").rglob("*.parquet"))
    if not files:
        raise SystemExit(f"no Parquet files under {args.first / 'points'}")
    print(f"{'frame':<28}{'points A':>10}{'points B':>10}  {'sha256(sorted xyz) A':<18}{'B':<18}"
          f"{'tables':>8}{'metadata':>10}{'PLY':>6}")
    for path in files:
        relative = path.relative_to(args.first / "points")
        other = args.second / "points" / relative
        a, b = pq.read_table(path), pq.read_table(other)
        xyz_a, xyz_b = (np.column_stack([t[c].to_numpy() for c in "xyz"]) for t in (a, b))
        meta_a, meta_b = ({k: v for k, v in (pq.read_metadata(p).metadata or {}).items() if k != ARROW_SCHEMA_KEY}
                          for p in (path, other))
        ply_a = args.first / "ply" / relative.with_suffix(".ply")
        ply_b = args.second / "ply" / relative.with_suffix(".ply")
        same_ply = ply_a.is_file() and ply_b.is_file() and ply_a.read_bytes() == ply_b.read_bytes()
        equal = a.equals(b)
        print(f"{str(relative.with_suffix('')):<28}{a.num_rows:>10,}{b.num_rows:>10,}  {xyz_digest(xyz_a):<18}"
              f"{xyz_digest(xyz_b):<18}{'equal' if equal else 'DIFFER':>8}{'equal' if meta_a == meta_b else 'DIFFER':>10}"
              f"{'equal' if same_ply else 'DIFFER':>6}")
        if not equal and len(xyz_a) == len(xyz_b):
            print(f"  largest |difference| of x, y, z: {np.abs(xyz_a.astype(np.float64) - xyz_b).max():.3g} m")


if __name__ == "__main__":
    main()
