"""Ground removal per simulated scene type and on the real scans: agreement with Patchwork++, F1.

    python bench/ground_scenes.py [--seeds 8] [--scene-types urban,suburban,open]
                                  [--methods patchwork,ransac] [--params '{"neighbour_step": 0.0, "resume_after_dips": false}']
                                  [--data ../shared/data/kitti/odometry/sequences/00] [--by-class]

Needs the optional `pypatchworkpp` (`pip install "kitti-pu[patchwork]"`). For each scene type of
`cadpu.synthetic.scenes` and each of `--seeds` held-out seeds (from 5,000, as
`bench/simulated_scans.py`), one simulated HDL-64E scan at x = 10 + 12 (i mod 5) m along the road,
heading alternately along and against it. Per scene type and method: agreement with Patchwork++'s
labels (percent of points labelled the same; median and minimum over the seeds), F1 of the ground
label against the simulator's labels (median; SemanticKITTI scoring as `bench/ground.py`: ground =
road, sidewalk, terrain; vegetation left out), and the recall of the elevated ground, the sidewalk
and terrain points 15-30 m out lying 0.05-0.3 m above the road (median), and where the method and
Patchwork++ differ, the share where Patchwork++ contradicts the simulator's labels ("pp wrong",
median; vegetation left out). Then the same methods on the real scans of `--data`: agreement with
Patchwork++ per frame and F1 on the labelled frames. `--params` sets parameters of the default
method (`stages.ground.PatchworkParams`); `'{"neighbour_step": 0.0, "resume_after_dips": false}'` is
the method before steps 5b and 5c. `--by-class` adds, per scene type, where the first method and
Patchwork++ differ: the share of all points of each simulator class that only the method calls
ground, and that only Patchwork++ calls ground (summed over the seeds).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from cadpu.synthetic.lidar import SceneCaster, ScanResult, mount_pose, simulate_scan
from cadpu.synthetic.scenes import SCENE_TYPES, make_scene
from cadpu.synthetic.street import CLASS_NAMES, SEMANTIC_KITTI, SIDEWALK, TERRAIN, VEGETATION, is_ground
from ground import DEFAULT_DATA, load, score  # bench/ground.py, beside this script
from stages import ground as ground_stage

FIRST_SEED = 5000
ELEVATED_RANGE = (15.0, 30.0)  # metres, horizontal
ELEVATED_HEIGHT = (0.05, 0.3)  # metres above the road under the sensor


@contextmanager
def quiet_stdout():
    """Silence writes to file descriptor 1 (Patchwork++ prints a line per estimator it builds)."""
    sys.stdout.flush()
    saved, devnull = os.dup(1), os.open(os.devnull, os.O_WRONLY)
    os.dup2(devnull, 1)
    try:
        yield
    finally:
        os.dup2(saved, 1)
        os.close(devnull)
        os.close(saved)


def simulated(scene_type: str, index: int) -> ScanResult:
    """The held-out scan `index` of a scene type (see the module docstring)."""
    seed = FIRST_SEED + index
    scene = make_scene(scene_type, seed)
    pose = mount_pose(scene, 10.0 + 12.0 * (index % 5), yaw=float(np.pi * (index % 2)))
    return simulate_scan(SceneCaster(scene), pose, seed=seed)


def elevated_ground(scan: ScanResult) -> np.ndarray:
    """(N,) bool: the sidewalk and terrain points of `ELEVATED_RANGE` lying `ELEVATED_HEIGHT` above
    the road under the sensor (the road is at z = -1.73 m in the sensor frame, slope aside)."""
    xyz = scan.points[:, :3].astype(np.float64)
    reach = np.hypot(xyz[:, 0], xyz[:, 1])
    rise = xyz[:, 2] + 1.73
    return (np.isin(scan.labels, (SIDEWALK, TERRAIN)) & (reach >= ELEVATED_RANGE[0]) & (reach < ELEVATED_RANGE[1])
            & (rise >= ELEVATED_HEIGHT[0]) & (rise < ELEVATED_HEIGHT[1]))


def _reference_wrong_share(mask: np.ndarray, reference: np.ndarray, scan: ScanResult) -> float:
    """Of the points where `mask` and Patchwork++'s `reference` differ, the fraction where
    Patchwork++ contradicts the simulator's labels (vegetation, which either may call ground, left
    out); 0 when they agree everywhere."""
    differ = (mask != reference) & (scan.labels != VEGETATION)
    if not differ.any():
        return 0.0
    return float((reference[differ] != is_ground(scan.labels[differ])).mean())


def disagreement_by_class(masks: list[np.ndarray], reference: list[np.ndarray], scans: list[ScanResult]
                          ) -> list[tuple[str, float, float]]:
    """Per simulator class where the method's and Patchwork++'s ground masks differ: (class name,
    percent of all points that only the method calls ground, percent only Patchwork++ does), over
    all scans together, classes without a difference left out."""
    classes = len(CLASS_NAMES)
    only_method, only_reference = np.zeros(classes), np.zeros(classes)
    for m, r, scan in zip(masks, reference, scans):
        only_method += np.bincount(scan.labels[m & ~r], minlength=classes)[:classes]
        only_reference += np.bincount(scan.labels[~m & r], minlength=classes)[:classes]
    total = sum(len(scan.labels) for scan in scans)
    return [(name, 100 * mine / total, 100 * theirs / total)
            for name, mine, theirs in zip(CLASS_NAMES, only_method, only_reference) if mine or theirs]


def segment(points: np.ndarray, method: str, params: dict) -> np.ndarray:
    """The method's ground mask; `params` only for the default method."""
    chosen = ground_stage.PatchworkParams(**params) if method == "patchwork" and params else None
    with quiet_stdout():
        return ground_stage.segment(points, method, chosen).mask


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=8)
    parser.add_argument("--scene-types", default=",".join(SCENE_TYPES))
    parser.add_argument("--methods", default="patchwork")
    parser.add_argument("--params", default="{}", help="JSON object of PatchworkParams fields")
    parser.add_argument("--data", type=Path, default=DEFAULT_DATA)
    parser.add_argument("--by-class", action="store_true", help="where the first method and Patchwork++ differ, by class")
    args = parser.parse_args()
    methods, params = args.methods.split(","), json.loads(args.params)
    print(f"{args.seeds} seeds per scene type; default-method parameters changed: {params or 'none'}")
    print(f"{'scene':<9} {'method':<12} {'agree med %':>11} {'agree min %':>11} {'F1 med':>7} {'F1 min':>7} "
          f"{'elevated recall med %':>21} {'pp wrong med %':>15}")
    for scene_type in args.scene_types.split(","):
        scans = [simulated(scene_type, i) for i in range(args.seeds)]
        reference = [segment(scan.points, "patchworkpp", {}) for scan in scans]
        for method in methods + ["patchworkpp"]:
            masks = [segment(scan.points, method, params) for scan in scans]
            agree = [100 * float((m == r).mean()) for m, r in zip(masks, reference)]
            f1 = [score(m, SEMANTIC_KITTI[scan.labels])[2] for m, scan in zip(masks, scans)]
            elevated = [100 * float(m[elevated_ground(scan)].mean()) for m, scan in zip(masks, scans)
                        if elevated_ground(scan).any()]
            pp_wrong = [100 * _reference_wrong_share(m, r, scan) for m, r, scan in zip(masks, reference, scans)]
            print(f"{scene_type:<9} {method:<12} {np.median(agree):>11.2f} {min(agree):>11.2f} {np.median(f1):>7.2f} "
                  f"{min(f1):>7.2f} {np.median(elevated) if elevated else float('nan'):>21.1f} "
                  f"{np.median(pp_wrong):>15.1f}")
            if args.by_class and method == methods[0]:
                differences = disagreement_by_class(masks, reference, scans)
                print("  where they differ, % of all points: " + "; ".join(
                    f"{name} {mine:.2f} ground only by {method}, {theirs:.2f} only by patchworkpp"
                    for name, mine, theirs in differences))
    real, labels = load(args.data)
    reference = {name: segment(points, "patchworkpp", {}) for name, points in real.items()}
    print(f"real scans of {args.data}: agreement with Patchwork++ per frame (%), F1 on the labelled frames")
    for method in methods:
        masks = {name: segment(points, method, params) for name, points in real.items()}
        agree = " ".join(f"{name}={100 * float((masks[name] == reference[name]).mean()):.2f}" for name in real)
        f1 = " ".join(f"{name}={score(masks[name], lab)[2]:.2f}" for name, lab in labels.items())
        print(f"  {method:<12} agreement {agree}; F1 {f1}")


if __name__ == "__main__":
    main()
