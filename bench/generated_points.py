"""Where each method puts its new points in the 16-to-64-beam evaluation: how far they are from the
full scan, and how far from the input point they grew from.

For each scan, rings 0, 4, 8, ... are kept (`pipeline.evaluation.methods.thin_scan`) and densified 4x by
the shipped CAD-PU, the alpha = 1.0 network and the midpoint baseline, through the pipeline's own
stages and default settings. For the new points that fall in the non-ground region of the full
scan, it prints:

- "to full scan": mean distance to the nearest non-ground point of the full 64-ring scan, metres
  (how accurate the new points are);
- "offset / radius": median distance from the parent input point, in units of the parent's
  distance to its 12th nearest input neighbour, both measured in the tiled coordinates (z scaled by
  `tile.vertical_scale`) where the network works (how far the new points spread).

    python bench/generated_points.py ../shared/data/kitti/odometry/sequences/00 --frames 2
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pipeline.chain import Chain
from pipeline.config import PipelineConfig
from pipeline.evaluation.methods import MIDPOINT, MidpointUpsampler, load_models, thin_scan
from stages import ground, load, stitch, upsample
from stages.upsample import PatchUpsampler

NEIGHBOURS = 12


def new_point_figures(points: np.ndarray, models: dict[str, PatchUpsampler], config: PipelineConfig,
                      source: str) -> dict[str, tuple[float, float, int]]:
    """{method: (mean distance to the full scan in metres, median offset / radius, new points in
    the non-ground region)} for one full (N, 4) scan in KITTI order."""
    thinned, _ = thin_scan(points, source, ratio=config.upsample.ratio)
    full_ground = ground.segment(points, config.ground.method, config.ground.method_params()).mask
    full_xyz = np.asarray(points[:, :3], dtype=np.float64)
    full_tree = cKDTree(full_xyz)
    non_ground_tree = cKDTree(full_xyz[~full_ground])
    frame = load.frame_from_points(thinned, dataset="bench", sequence="bench")
    for step in Chain(config, writes=False).steps[1:3]:  # ground, tile
        frame = step(frame)
    tiled = np.array([1.0, 1.0, config.tile.vertical_scale])
    objects = np.flatnonzero(~frame.ground)
    object_xyz = thinned[objects, :3].astype(np.float64) * tiled
    radius = cKDTree(object_xyz).query(object_xyz, k=NEIGHBOURS + 1)[0][:, -1]  # +1: the point itself
    slot = np.full(len(thinned), -1)
    slot[objects] = np.arange(len(objects))
    figures = {}
    for name, model in models.items():
        cloud = stitch.stitch(upsample.run(frame, config.upsample, upsampler=model), keep_input=False)
        new = cloud.xyz[cloud.generated].astype(np.float64)
        parent = cloud.parent[cloud.generated]
        offset = np.linalg.norm(new * tiled - thinned[parent, :3] * tiled, axis=1) / radius[slot[parent]]
        # New: in the full scan's non-ground region, and not a copy of its parent (the midpoint
        # baseline returns its input points among its output).
        keep = ~full_ground[full_tree.query(new)[1]] & (offset > 0)
        to_full = non_ground_tree.query(new[keep])[0]
        figures[name] = (float(to_full.mean()), float(np.median(offset[keep])), int(keep.sum()))
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("data", type=Path, help="a KITTI sequence, drive or folder of .bin scans")
    parser.add_argument("--frames", type=int, default=2, help="first N scans")
    args = parser.parse_args()
    config = PipelineConfig()
    models: dict[str, PatchUpsampler] = {**load_models(None, None, config)[0], MIDPOINT: MidpointUpsampler()}
    print(f"{'scan':<22} {'method':<20} {'new points':>10} {'to full scan m':>15} {'offset / radius':>16}")
    for ref in load.discover(args.data)[:args.frames]:
        points = load.read_scan(ref.source, config.input.max_points)
        for name, (distance, offset, count) in new_point_figures(points, models, config, ref.source).items():
            print(f"{ref.key:<22} {name:<20} {count:>10,} {distance:>15.4f} {offset:>16.2f}")


if __name__ == "__main__":
    main()
