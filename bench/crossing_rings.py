"""Ring snapping where rings cross: in how many azimuth columns of a scan two rings cross (seen from
the origin), how many generated points lie there, and whether snapping a snapped cloud moves or
drops points again (`stages.ring_snap`; docs/results.md, "Rings that cross").

    python bench/crossing_rings.py DIR [DIR ...] [--inputs CACHE] [--compare main]

For every scan (`*.bin`, KITTI order) of each folder, two inputs: the 16-ring scan of `kitti-pu
eval-kitti` (rings 0, 4, 8, ...) and the full 64-ring scan of `kitti-pu run`. Each goes through
the chain with the defaults up to the stitch stage (the shipped network; with --inputs the
generated points are kept in CACHE and reused, so the network runs once and both sides of
--compare snap the same points), then through `snap_and_check` as the snap stage calls it, and
its output through it again. Figures, summed over the scans of each input kind:

- crossing columns: azimuth columns (2000) of `ring_tables` where some ring lies above the ring
  listed before it;
- generated, in crossing: the network's points, and those whose azimuth falls in such a column;
- kept: points the snap stage keeps;
- moved again / dropped again: of those, moved by more than 0.1 mm or dropped by a second
  `snap_and_check`; "nearest moved again": moved by a second `snap_to_virtual_rings`; each also
  counted in crossing columns only;
- off the ordered rings: kept points not on a virtual ring (1e-6 rad) of any gap between the
  returns of their column taken in elevation order (numpy here, not the stage's code);
- non-crossing digest: crc32 of the snapped points and the keep flags of the points outside
  crossing columns (equal on two revisions: equal output there, bit for bit).

With --compare REF the script runs on git revision REF and on the working tree (`bench/revisions.py`).
"""

from __future__ import annotations

import argparse
import zlib
from pathlib import Path

import numpy as np

import revisions
from pipeline.chain import Chain
from pipeline.config import PipelineConfig
from stages import load, ring_snap
from stages.rings import keep_rings, recover_rings

RATIO = 4
MOVED_M = 1e-4
TOLERANCE_M = 0.05


def generated_points(points: np.ndarray, cache: Path | None) -> np.ndarray:
    """(Q, 3) float32 the network's points of the stitched cloud of `points` (defaults), from
    `cache` when there (else computed and, with a cache path, saved there)."""
    if cache is not None and cache.exists():
        return np.load(cache)
    frame: object = load.frame_from_points(points)
    for step in Chain(PipelineConfig(), writes=False).steps:
        if step.name == "snap":
            break
        if step.name != "load":
            frame = step(frame)
    xyz = frame.cloud.xyz[frame.cloud.generated]  # type: ignore[attr-defined]
    if cache is not None:
        cache.parent.mkdir(parents=True, exist_ok=True)
        np.save(cache, xyz)
    return xyz


def column_of(xyz: np.ndarray, width: int) -> np.ndarray:
    """(Q,) azimuth column of each point, as `stages.ring_kernels.gaps_of` bins it."""
    xyz = np.asarray(xyz, np.float64)
    return np.floor((np.arctan2(xyz[:, 1], xyz[:, 0]) + np.pi) / (2 * np.pi) * width).astype(np.int64) % width


def off_ordered_rings(xyz: np.ndarray, elevation: np.ndarray) -> np.ndarray:
    """(Q,) whether each point lies off every virtual ring of its column's returns in elevation order."""
    table = -np.sort(-elevation, axis=0)
    values = table[:, column_of(xyz, table.shape[1])]
    xyz = np.asarray(xyz, np.float64)
    e = np.arcsin(np.clip(xyz[:, 2] / np.linalg.norm(xyz, axis=1), -1.0, 1.0))
    steps = (np.arange(1, RATIO) / RATIO)[:, None, None]
    virtual = values[None, :-1] + (values[None, 1:] - values[None, :-1]) * steps
    return np.abs(virtual - e[None, None]).min(axis=(0, 1)) >= 1e-6


def measure_scan(points: np.ndarray, xyz: np.ndarray) -> tuple[dict[str, float], bytes]:
    """Figures of one scan and its generated points, and the bytes of its non-crossing output."""
    tables = ring_snap.ring_tables(points, ring_snap.scan_rings(points))
    crossing = np.any(np.diff(tables.elevation, axis=0) > 0, axis=0)
    in_crossing = crossing[column_of(xyz, tables.elevation.shape[1])]
    snapped, keep = ring_snap.snap_and_check(xyz, tables, RATIO, TOLERANCE_M)
    kept = snapped[keep]
    again, keep_again = ring_snap.snap_and_check(kept, tables, RATIO, TOLERANCE_M)
    nearest, _ = ring_snap.snap_to_virtual_rings(kept, tables.elevation, RATIO)
    moved = np.abs(again - kept).max(axis=1, initial=0) > MOVED_M
    nearest_moved = np.abs(nearest - kept).max(axis=1, initial=0) > MOVED_M
    there = in_crossing[keep]
    figures = {"crossing columns": crossing.sum(), "generated": len(xyz), "generated in crossing": in_crossing.sum(),
               "kept": keep.sum(), "kept in crossing": keep[in_crossing].sum(),
               "moved again": moved.sum(), "moved again in crossing": moved[there].sum(),
               "dropped again": (~keep_again).sum(), "dropped again in crossing": (~keep_again)[there].sum(),
               "nearest moved again": nearest_moved.sum(), "nearest moved in crossing": nearest_moved[there].sum(),
               "off the ordered rings": off_ordered_rings(kept, tables.elevation).sum()}
    outside = snapped[~in_crossing].tobytes() + keep[~in_crossing].tobytes()
    return {name: float(value) for name, value in figures.items()}, outside


def measure(folders: list[Path], inputs: Path | None) -> dict[str, float]:
    """The figures of every scan of `folders`, summed per input kind ("16-ring: ...", "64-ring: ...")."""
    figures: dict[str, float] = {}
    for kind in ("16-ring", "64-ring"):
        digest = 0
        for folder in folders:
            for path in sorted(folder.glob("*.bin")):
                points = load.read_scan(path)
                if kind == "16-ring":
                    points = keep_rings(points, recover_rings(points), ratio=RATIO)
                cache = None if inputs is None else inputs / f"{folder.name}-{path.stem}-{kind}.npy"
                scan_figures, outside = measure_scan(points, generated_points(points, cache))
                for name, value in scan_figures.items():
                    figures[f"{kind}: {name}"] = figures.get(f"{kind}: {name}", 0.0) + value
                digest = zlib.crc32(outside, digest)
        figures[f"{kind}: non-crossing digest"] = float(digest)
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("folders", type=Path, nargs="+", help="folders of KITTI-ordered .bin scans")
    parser.add_argument("--inputs", type=Path, default=None, help="folder keeping the network's points per scan")
    revisions.add_arguments(parser)
    args = revisions.parse_or_compare(parser, Path(__file__))
    if args is None:
        return
    figures = measure(args.folders, args.inputs)
    if args.json:
        revisions.emit(figures)
        return
    for name, value in figures.items():
        print(f"{name:<40}{value:>14.0f}")


if __name__ == "__main__":
    main()
