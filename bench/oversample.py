"""How many candidates per kept point (`Upsampler(oversample=M)`) the object networks should make,
and how far from their parents (`Upsampler(offset_scale=S)`).

The paper's protocol as `python -m cadpu.evaluate` runs it (2,048 input points, 8 clusters of 256,
4x), without the Poisson step: each weights file at each oversampling of `--oversample` and each
offset scale of `--offset-scale`, beside the midpoint baseline, on held-out procedural meshes
(`--first-mesh`: 0-19 are where the defaults were chosen, 20 on confirm them) and the PU-GAN test
meshes of a folder. Prints the means over the meshes of CD, HD and P2F (x 1e-3, unit sphere) and
each one's gain over the baseline.

    python bench/oversample.py --meshes 20 --first-mesh 0
    python bench/oversample.py --meshes 20 --first-mesh 20 --pugan ../shared/data/pugan --oversample 1,2
    python bench/oversample.py --meshes 20 --first-mesh 0 --weights cadpu_r4 --oversample 2 \
        --offset-scale 1,1.2,1.4

The baseline's P2F is printed beside each method's as a ratio (issue 18 asks it be no worse), and
how far each method's points lie from the nearest input point, beside uniform samples of the
surface (the reach an even cover of the surface would have).
"""

from __future__ import annotations

import argparse
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch
from scipy.spatial import cKDTree

from cadpu import baseline
from cadpu.evaluate import SURFACE_SAMPLES, TestCase, held_out_cases, pugan_cases, upsample_by_clusters
from cadpu.inference import MAX_OVERSAMPLE, Upsampler
from cadpu.metrics import chamfer_distance, hausdorff_distance, point_to_surface
from cadpu.synthetic.shapes import sample_surface


def from_inputs(case: TestCase, points: np.ndarray) -> float:
    """Mean distance from each of `points` to the nearest input point of `case` (unit sphere)."""
    return float(cKDTree(case.inputs).query(points)[0].mean())


def scores(cases: list[TestCase], upsample: Callable[[np.ndarray], np.ndarray]) -> np.ndarray:
    """(meshes, 4): CD, HD, mean P2F and `from_inputs` of each case's output, in the unit sphere."""
    rows = []
    for case in cases:
        truth, _ = sample_surface(case.mesh, SURFACE_SAMPLES, np.random.default_rng(0))
        output = upsample_by_clusters(case.inputs, upsample)
        rows.append((chamfer_distance(output, truth), hausdorff_distance(output, truth),
                     float(point_to_surface(output, case.mesh.vertices, case.mesh.triangles).mean()),
                     from_inputs(case, output)))
    return np.array(rows)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--meshes", type=int, default=20, help="held-out procedural meshes")
    parser.add_argument("--first-mesh", type=int, default=0, help="index of the first held-out mesh")
    parser.add_argument("--pugan", type=Path, default=None, help="folder of PU-GAN test meshes (.off)")
    parser.add_argument("--weights", default="cadpu_r4,cadpu_r4_alpha1", help="comma-separated files or names")
    parser.add_argument("--oversample", default="1,2,3,4", help=f"comma-separated, each 1 to {MAX_OVERSAMPLE}")
    parser.add_argument("--offset-scale", default="1", help="comma-separated factors on each generated "
                                                            "point's distance from its parent")
    args = parser.parse_args()
    if args.pugan is not None and not args.pugan.is_dir():
        raise SystemExit(f"oversample: --pugan {args.pugan} is not a folder")
    try:
        factors = [int(value) for value in args.oversample.split(",")]
    except ValueError:
        raise SystemExit(f"oversample: --oversample {args.oversample!r} is not a list of whole numbers") from None
    try:
        scales = [float(value) for value in args.offset_scale.split(",")]
    except ValueError:
        raise SystemExit(f"oversample: --offset-scale {args.offset_scale!r} is not a list of numbers") from None
    cases = held_out_cases(args.meshes, first=args.first_mesh) + (pugan_cases(args.pugan) if args.pugan else [])
    if not cases:
        raise SystemExit("oversample: no meshes (give --meshes N or --pugan DIR)")
    torch.set_num_threads(1)
    methods: dict[str, Callable[[np.ndarray], np.ndarray]] = {
        "midpoint baseline": lambda patches: baseline.upsample_patches(patches, 4)[0]}
    for weights in args.weights.split(","):
        for factor in factors:
            for scale in scales:
                try:
                    model = Upsampler(weights, oversample=factor, offset_scale=scale)
                except ValueError as error:
                    raise SystemExit(f"oversample: {error}") from None
                methods[f"{Path(weights).stem} x{factor} s{scale:g}"] = (
                    lambda m: (lambda patches: m.upsample_patches(patches)[0]))(model)
    print(f"{len(cases)} meshes ({', '.join(c.name for c in cases[:3])}, ...), x 1e-3 (unit sphere), means")
    print(f"{'method':<28} {'CD':>7} {'HD':>7} {'P2F':>6} {'CD gain':>8} {'HD gain':>8} {'P2F / baseline':>15} "
          f"{'from input':>11}")
    reference = None
    for name, upsample in methods.items():
        cd, hd, p2f, reach = scores(cases, upsample).mean(axis=0)
        reference = reference if reference is not None else (cd, hd, p2f)
        print(f"{name:<28} {1e3 * cd:>7.3f} {1e3 * hd:>7.2f} {1e3 * p2f:>6.3f} "
              f"{100 * (1 - cd / reference[0]):>7.1f}% {100 * (1 - hd / reference[1]):>7.1f}% {p2f / reference[2]:>15.2f} "
              f"{1e3 * reach:>11.2f}")
    # how far from the input points the surface itself lies, sampled as densely as the outputs
    surface = np.mean([from_inputs(case, sample_surface(case.mesh, len(case.inputs) * 4, np.random.default_rng(1))[0])
                       for case in cases])
    print(f"from input: mean distance of a method's points to the nearest input point; of {4 * len(cases[0].inputs):,} "
          f"uniform samples of each surface, {1e3 * surface:.2f}")


if __name__ == "__main__":
    main()
