"""Write simulated HDL-64E scans of held-out procedural streets as a folder of KITTI `.bin` files.

The scans are in KITTI point order, so `kitti-pu eval-kitti FOLDER` runs the 16-to-64-beam
evaluation on them exactly as on real scans. Street seeds start at 5,000 (training streets use
seeds from 0); scan i is taken at x = 10 + 12 i metres, heading alternately along and against the
street. `--scene-type` picks the scene type of `cadpu.synthetic.scenes` (urban, the default, suburban,
open, rural, residential: the one made to match KITTI's scene statistics). This is the data the pipeline's settings are chosen on (the urban scans: `upsample.max_patch_radius`,
for one):

    python bench/simulated_scans.py /tmp/sim
    for r in 3 4 5 6 8 0; do kitti-pu eval-kitti /tmp/sim --out /tmp/sim-eval-$r --set upsample.max_patch_radius=$r; done

The sensor is the HDL-64E as measured on real KITTI scans (`cadpu.synthetic.lidar.HDL64E`,
bench/sim_vs_real.py); `--sensor clean` writes the scans of the idealised sensor that the settings
chosen before it (docs/results.md) were chosen on, bit for bit.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import numpy as np

from cadpu.synthetic.lidar import (HDL64E, HDL64E_RANGE_BIASED, LidarModel, ScanResult, SceneCaster, mount_pose,
                                  simulate_scan)
from cadpu.synthetic.scenes import SCENE_TYPES, make_scene

FIRST_SEED = 5000


def held_out_scan(i: int, first_seed: int = FIRST_SEED, scene_type: str = "urban",
                  model: LidarModel = HDL64E) -> ScanResult:
    """Scan i of the held-out series: scene seed first_seed + i, taken at x = 10 + 12 i metres,
    heading alternately along and against the street."""
    seed = first_seed + i
    scene = make_scene(scene_type, seed)
    pose = mount_pose(scene, 10.0 + 12.0 * i, yaw=float(np.pi * (i % 2)))
    return simulate_scan(SceneCaster(scene), pose, seed=seed, model=model)


def write_scans(folder: Path, count: int = 6, scene_type: str = "urban", model: LidarModel = HDL64E) -> list[Path]:
    """Simulate `count` scans (one per scene seed) of `scene_type` with the sensor `model` and write them as
    `<folder>/<i:06d>.bin`.

    Returns:
        The paths written, float32 x, y, z, reflectance per point, sensor frame, metres.
    """
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for i in range(count):
        scan = held_out_scan(i, FIRST_SEED, scene_type, model)
        path = folder / f"{i:06d}.bin"
        scan.points.astype(np.float32).tofile(path)
        paths.append(path)
    return paths


#: The sensors `--sensor` offers.
SENSORS = {"measured": lambda: HDL64E, "range-biased": lambda: HDL64E_RANGE_BIASED, "clean": LidarModel.clean}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("folder", type=Path)
    parser.add_argument("--count", type=int, default=6)
    parser.add_argument("--scene-type", choices=SCENE_TYPES, default="urban")
    parser.add_argument("--sensor", choices=tuple(SENSORS), default="measured",
                        help="the HDL-64E as measured on real scans; the same with KITTI's per-laser range "
                             "biases; or the idealised sensor used before")
    args = parser.parse_args()
    model = SENSORS[args.sensor]()
    for path in write_scans(args.folder, args.count, args.scene_type, model):
        print(path)


if __name__ == "__main__":
    main()
