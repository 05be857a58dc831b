"""Which of each method's new points land where the full scan has points, by the kind of ring gap
they were put in and by range: where range-image interpolation wins the voxel F1.

For each scan, rings 0, 4, 8, ... are kept (`pipeline.evaluation.methods.thin_scan`) and densified
4x by range-image interpolation, the midpoint baseline and the pipeline's default network, as
`kitti-pu eval-kitti` does. Every new point (not an input point) in the non-ground region of the
full scan is located among the input's rings (`stages.ring_snap`): in a ring gap whose two returns
lie on one surface, or across a depth edge. It "hits" when its 0.1 m voxel holds a point of the
full scan (per point: eval-kitti's voxel precision counts each occupied voxel once). Printed per
method: the hit share of all new points, by gap kind, and by range band, with the counts.

    python bench/gap_hits.py /tmp/sim_rural --frames 3      # simulated scans: bench/simulated_scans.py
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from cadpu.metrics import occupied_voxels
from pipeline.config import PipelineConfig
from cadpu.inference import Upsampler
from pipeline.evaluation.methods import MIDPOINT, NETWORK, RANGE_IMAGE, method_outputs, thin_scan
from pipeline.evaluation.scoring import VOXEL_SIZE
from stages import ground, load
from stages.ring_snap import _locate, _range_fits, in_column_order, ring_tables
from stages.upsample import PatchUpsampler

#: Range bands of the table, metres.
BANDS = ((0.0, 10.0), (10.0, 20.0), (20.0, 40.0), (40.0, 200.0))
METHODS = (RANGE_IMAGE, MIDPOINT, NETWORK)


def new_point_hits(points: np.ndarray, network: PatchUpsampler, config: PipelineConfig, source: str
                   ) -> dict[str, tuple[np.ndarray, np.ndarray, np.ndarray]]:
    """{method: (hit, one_surface, range)} of each method's new non-ground points of one full
    (N, 4) scan in KITTI order, `network` the learned method: (Q,) bool, (Q,) bool, (Q,) metres."""
    thinned, rings = thin_scan(points, source, ratio=config.upsample.ratio)
    full_ground = ground.segment(points, config.ground.method, config.ground.method_params()).mask
    occupied = {tuple(v) for v in occupied_voxels(points[~full_ground, :3], VOXEL_SIZE)}
    nearest_label = cKDTree(points[:, :3])
    frame = load.frame_from_points(thinned, dataset="bench", sequence="gaps", source=source)
    outputs = method_outputs(frame, rings, {NETWORK: network}, config, ratio=config.upsample.ratio)
    tables = in_column_order(ring_tables(thinned, rings))
    inputs = {tuple(p) for p in np.round(thinned[:, :3], 4).tolist()}
    result = {}
    for method in METHODS:
        cloud = np.asarray(outputs[method][0], dtype=np.float64)
        _, nearest = nearest_label.query(cloud, k=1)
        new = np.array([tuple(p) not in inputs for p in np.round(cloud.astype(np.float32), 4).tolist()], dtype=bool)
        chosen = cloud[new & ~full_ground[nearest]]
        located = _locate(chosen, tables.elevation)
        _, one_surface = _range_fits(located, tables, config.snap.range_tolerance or 0.0)
        voxels = np.floor(chosen / VOXEL_SIZE).astype(np.int64)
        hit = np.array([tuple(v) in occupied for v in voxels.tolist()], dtype=bool)
        result[method] = (hit, one_surface & located.between, located.distance)
    return result


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("path", type=Path, help="folder of full 64-ring scans in KITTI order")
    parser.add_argument("--frames", type=int, default=3)
    args = parser.parse_args()
    config = PipelineConfig()
    try:
        refs = load.discover(args.path)[:args.frames]
    except load.InputError as error:
        raise SystemExit(f"gap_hits: {error}") from None
    if not refs:
        raise SystemExit(f"gap_hits: no scans under {args.path}")
    section = config.upsample
    network = Upsampler(section.weights, ratio=section.ratio, device=section.device, engine=section.engine,
                        oversample=section.oversample)
    parts: dict[str, list[tuple[np.ndarray, np.ndarray, np.ndarray]]] = {method: [] for method in METHODS}
    for ref in refs:
        for method, figures in new_point_hits(load.scan_points(ref.source), network, config, ref.source).items():
            parts[method].append(figures)
    print(f"{args.path}, {len(refs)} scans: share of new non-ground points in an occupied {VOXEL_SIZE} m voxel")
    for method in METHODS:
        hit, one, distance = (np.concatenate(column) for column in zip(*parts[method]))
        print(f"{method:<20} all {_share(hit)}; one surface {_share(hit[one])}; across edges {_share(hit[~one])}")
        for low, high in BANDS:
            band = (distance >= low) & (distance < high)
            print(f"    {low:>4.0f}-{high:<4.0f} m  {_share(hit[band])}; across edges {_share(hit[band & ~one])}")


def _share(hits: np.ndarray) -> str:
    """'0.123 (n N)': the share of True in `hits` and its count ('- (n 0)' when empty)."""
    return f"{hits.mean():.3f} (n {len(hits)})" if len(hits) else "- (n 0)"


if __name__ == "__main__":
    main()
