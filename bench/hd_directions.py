"""What makes the Hausdorff distance of upsampled objects: points off the surface, or surface far
from every point (holes the input left)?

The paper's protocol as `python -m cadpu.evaluate` runs it (2,048 input points, 8 clusters, 4x):
for held-out procedural meshes (numbers from 20 on, which the learning curves never score) and the
PU-GAN test meshes of a folder, each method's output against 100,000 points on the mesh. Printed
per method, means over the meshes, x 1e-3 in the unit sphere: HD, the two directed maxima (output
-> surface: points off it; surface -> output: holes), the two directed means, and on how many
meshes the output -> surface side sets HD. The row "input" is the 2,048 input points themselves:
their surface -> input maximum is the largest hole the input leaves.

    python bench/hd_directions.py --meshes 22 --pugan ../shared/data/pugan
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np

from cadpu import baseline
from cadpu.evaluate import SURFACE_SAMPLES, TestCase, held_out_cases, pugan_cases, upsample_by_clusters
from cadpu.inference import Upsampler
from cadpu.metrics import directed_distances
from cadpu.synthetic.shapes import sample_surface

#: First held-out mesh: 0-19 are the learning curves' (`cadpu.evaluate.held_out_cases`).
FIRST_MESH = 20


def directions(cases: list[TestCase], upsample: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """(meshes, 4): max and mean of output -> surface, max and mean of surface -> output."""
    rows = []
    for case in cases:
        surface, _ = sample_surface(case.mesh, SURFACE_SAMPLES, np.random.default_rng(0))
        output = upsample_by_clusters(case.inputs, upsample)
        off, holes = directed_distances(output, surface), directed_distances(surface, output)
        rows.append((off.max(), off.mean(), holes.max(), holes.mean()))
    return np.array(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", type=int, default=22, help="held-out procedural meshes")
    parser.add_argument("--pugan", type=Path, default=None, help="folder of PU-GAN test meshes (.off)")
    args = parser.parse_args()
    if args.pugan is not None and not args.pugan.is_dir():
        raise SystemExit(f"hd_directions: --pugan {args.pugan} is not a folder")
    cases = held_out_cases(args.meshes, first=FIRST_MESH) + (pugan_cases(args.pugan) if args.pugan else [])
    if not cases:
        raise SystemExit("hd_directions: no meshes (give --meshes N or --pugan DIR)")
    methods: dict[str, Callable[[np.ndarray], np.ndarray]] = {"input": lambda patches: patches}
    methods |= {
        name: (lambda model: (lambda patches: model.upsample_patches(patches)[0]))(Upsampler(name))
        for name in ("cadpu_r4", "cadpu_r4_alpha1")}
    methods["midpoint baseline"] = lambda patches: baseline.upsample_patches(patches, 4)[0]
    print(f"{len(cases)} meshes, x 1e-3 (unit sphere), means over the meshes")
    print(f"{'method':<20} {'HD':>7} {'off max':>8} {'holes max':>10} {'off mean':>9} {'holes mean':>11}  HD set by off")
    for name, upsample in methods.items():
        figures = directions(cases, upsample) * 1e3
        hd = np.maximum(figures[:, 0], figures[:, 2])
        by_off = int((figures[:, 0] > figures[:, 2]).sum())
        print(f"{name:<20} {hd.mean():>7.2f} {figures[:, 0].mean():>8.2f} {figures[:, 2].mean():>10.2f} "
              f"{figures[:, 1].mean():>9.3f} {figures[:, 3].mean():>11.3f}  {by_off}/{len(cases)}")


if __name__ == "__main__":
    main()
