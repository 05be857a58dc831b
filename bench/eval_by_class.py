"""The 16-to-64-beam evaluation split by SemanticKITTI class: on which surfaces each method helps.

For every scan of a sequence that has a `labels/<frame>.label` file, rings 0, 4, 8, ... are kept
and densified 4x by every method of `kitti-pu eval-kitti` (same stages, same default settings),
and the non-ground Chamfer distance is split by the class of the full-scan points:

- accuracy: mean distance from the output points whose nearest full-scan point has the class to
  the full scan's non-ground points, metres;
- completeness: mean distance from the full scan's non-ground points of the class to the output;
- their mean, the class's share of the Chamfer distance (the whole-region figure is printed last,
  as `kitti-pu eval-kitti` reports it).

    python bench/eval_by_class.py ../shared/data/kitti/odometry/sequences/00
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from pipeline.config import PipelineConfig
from pipeline.evaluation.methods import load_models, method_outputs, thin_scan
from stages import ground, load

#: SemanticKITTI classes reported on their own (label & 0xFFFF); everything else is "other".
CLASSES: dict[str, tuple[int, ...]] = {
    "car": (10,), "building": (50,), "fence": (51,), "vegetation": (70,), "trunk": (71,),
    "pole/sign": (80, 81),
}
OTHER = "other"


def class_of(labels: np.ndarray) -> np.ndarray:
    """(N,) SemanticKITTI labels (uint32, instance in the upper 16 bits) -> (N,) class names."""
    semantic = np.asarray(labels, dtype=np.uint32) & 0xFFFF
    names = np.full(len(semantic), OTHER, dtype=object)
    for name, ids in CLASSES.items():
        names[np.isin(semantic, ids)] = name
    return names


def split_chamfer(output: np.ndarray, full: np.ndarray, full_ground: np.ndarray,
                  classes: np.ndarray) -> dict[str, tuple[float, float, int]]:
    """The non-ground Chamfer distance of one output, split by class.

    Args:
        output: (Q, 3) output cloud, sensor frame, metres.
        full: (N, 3) full scan. full_ground: (N,) bool its ground mask. classes: (N,) class names.

    Returns:
        {class: (accuracy m, completeness m, full-scan points of the class)}, plus "all" with the
        whole region's figures (accuracy is NaN for a class no output point is nearest to).
    """
    full = np.asarray(full, dtype=np.float64)
    output = np.asarray(output, dtype=np.float64)[:, :3]
    # The region split of `pipeline.evaluation.scoring.Reference`: an output point is non-ground when its
    # nearest full-scan point is.
    output = output[~full_ground[cKDTree(full).query(output, workers=-1)[1]]]
    region, region_classes = full[~full_ground], classes[~full_ground]
    accuracy, nearest = cKDTree(region).query(output, workers=-1)
    completeness, _ = cKDTree(output).query(region, workers=-1)
    figures = {}
    for name in (*CLASSES, OTHER):
        of_output, of_full = region_classes[nearest] == name, region_classes == name
        figures[name] = (float(accuracy[of_output].mean()) if of_output.any() else float("nan"),
                         float(completeness[of_full].mean()) if of_full.any() else float("nan"),
                         int(of_full.sum()))
    figures["all"] = (float(accuracy.mean()), float(completeness.mean()), len(region))
    return figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("sequence", type=Path, help="a KITTI odometry sequence with velodyne/ and labels/")
    args = parser.parse_args()
    config = PipelineConfig()
    models, _ = load_models(None, None, config)
    labelled = sorted((args.sequence / "labels").glob("*.label"))
    if not labelled:
        sys.exit(f"eval_by_class: no labels/*.label files under {args.sequence}")
    for label_path in labelled:
        scan_path = args.sequence / "velodyne" / f"{label_path.stem}.bin"
        # read as stored, not through load.scan_points, which drops out-of-range returns: the labels
        # are one per stored point (the six real scans have none out of range)
        points = np.fromfile(scan_path, dtype=np.float32).reshape(-1, 4)
        classes = class_of(np.fromfile(label_path, dtype=np.uint32))
        if len(classes) != len(points):
            sys.exit(f"eval_by_class: {label_path} has {len(classes)} labels for {len(points)} points")
        thinned, rings = thin_scan(points, str(scan_path), ratio=config.upsample.ratio)
        full_ground = ground.segment(points, config.ground.method, config.ground.method_params()).mask
        frame = load.frame_from_points(thinned, dataset="bench", sequence="bench", source=str(scan_path))
        outputs = method_outputs(frame, rings, models, config, ratio=config.upsample.ratio)
        split = {name: split_chamfer(cloud, points[:, :3], full_ground, classes) for name, (cloud, _) in outputs.items()}
        columns = [*CLASSES, OTHER, "all"]
        counts = next(iter(split.values()))
        print(f"{scan_path}: accuracy / completeness -> their mean (m), non-ground region")
        print(f"{'class (full-scan points)':<24}" + "".join(f"{f'{c} ({counts[c][2]:,})':>25}" for c in columns))
        for name, figures in split.items():
            cells = [f"{a:.3f} / {c:.3f} -> {0.5 * (a + c):.3f}" for a, c, _ in (figures[col] for col in columns)]
            print(f"{name:<24}" + "".join(f"{cell:>25}" for cell in cells))


if __name__ == "__main__":
    main()
