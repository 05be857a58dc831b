"""Learning curves on held-out data: how a training run's network scores, every few thousand
samples, on data it never trains on, beside the non-learned midpoint baseline (`cadpu.baseline`).

Loss curves say whether the optimiser is still moving; these say whether more samples still pay.
The sets are fixed for a run and scored deterministically:

- "meshes": `cadpu.evaluate.held_out_cases` (procedural meshes, seeds from TEST_SEED_BASE, never
  trained on), the paper's protocol (2,048 -> 8,192 points through 8 clusters): CD and HD against
  100,000 points on the mesh, P2F to the mesh (no Poisson reconstruction: too slow to repeat);
- "pugan": the PU-GAN test meshes of a folder, when one is given (`cadpu.evaluate.pugan_cases`);
- "streets": pairs of simulated scans of urban streets never trained on (seeds from
  HELDOUT_STREET_SEED, `cadpu.scan_data`): Chamfer distance between output and truth in the pairs'
  unit spheres ("CD"), and after ring snapping in metres over the patch radius ("snapped CD",
  `cadpu.validation.snapped_chamfers`: what the pipeline's output is scored by, and what
  `objective: snapped_chamfer` trains); "streets-TYPE" the same for each other scene type a run
  trains on (suburban, open, rural: `cadpu.synthetic.scenes`).

Every call appends rows (step, samples_seen, set, metric, network, baseline) to a CSV, which long
runs keep beside their checkpoint in the repository, so the curve grows across sessions.
`python -m cadpu.curves CSV PNG` plots it.
"""

from __future__ import annotations

import argparse
import csv
from collections.abc import Callable
from pathlib import Path

import numpy as np
import torch

from . import baseline
from .data import PatchSet, sensor_model
from .evaluate import SURFACE_SAMPLES, TestCase, held_out_cases, pugan_cases, upsample_by_clusters
from .metrics import chamfer_distance, hausdorff_distance, point_to_surface
from .network import Generator
from .scan_data import street_scan_pairs
from .synthetic.shapes import sample_surface
from .validation import generated, pair_chamfers, snapped_chamfers

#: Street seeds of the held-out scans; training recipes use streets first_seed .. first_seed + streets - 1.
HELDOUT_STREET_SEED = 50_000
CURVE_COLUMNS = ("step", "samples_seen", "set", "metric", "network", "baseline")
MESH_METRICS = ("CD", "HD", "P2F")


class HeldoutCurves:
    """The held-out sets of a run and their baseline scores (computed once).

    Args:
        meshes: held-out procedural meshes (0 for none). streets: held-out streets of each scene
            type (2 scans each, 20 pairs a scan; 0 for none). vertical_scale: z factor the street
            pairs are cut with (the recipe's `data.scan_vertical_scale`). pugan: folder of PU-GAN
            test meshes, or None.
        sensor: the simulated LiDAR of the street scans (the recipe's `data.sensor`), so that a
            run's held-out streets come from the sensor it trains on.
        scene_types: the scene types of the held-out streets (the recipe's `data.scene_types`):
            set "streets" for urban, "streets-TYPE" for each other.
    """

    def __init__(self, meshes: int = 20, streets: int = 2, vertical_scale: float = 1.0,
                 pugan: Path | None = None, sensor: str = "measured",
                 scene_types: tuple[str, ...] = ("urban",)) -> None:
        self.mesh_sets: dict[str, list[tuple[TestCase, np.ndarray]]] = {}
        if meshes:
            self.mesh_sets["meshes"] = [(case, _truth(case)) for case in held_out_cases(meshes)]
        if pugan is not None:
            self.mesh_sets["pugan"] = [(case, _truth(case)) for case in pugan_cases(pugan)]
        self.street_sets: dict[str, PatchSet] = {}
        if streets:
            model = sensor_model(sensor)
            for scene_type in scene_types:
                parts = [street_scan_pairs(HELDOUT_STREET_SEED + i, 2, 20, vertical_scale, model, scene_type)
                         for i in range(streets)]
                self.street_sets[street_set_name(scene_type)] = PatchSet.concatenate(
                    [PatchSet(inputs, truth, normals, np.ones(len(inputs), dtype=bool), frames)
                     for inputs, truth, normals, frames in parts])
        self.baseline = self._scores(lambda p: baseline.upsample_patches(p, 4)[0], None)

    def score(self, generator: Generator) -> dict[tuple[str, str], float]:
        """{(set, metric): value} of `generator` (left in eval mode), distances in unit-sphere units."""
        device = next(generator.parameters()).device
        sampler = torch.Generator(device=device).manual_seed(0)
        generator.eval()

        @torch.no_grad()
        def upsample(patches: np.ndarray) -> np.ndarray:
            return generator(torch.from_numpy(patches).to(device), generator=sampler)[0].cpu().numpy()

        return self._scores(upsample, generator)

    def record(self, generator: Generator, step: int, samples_seen: int, path: Path) -> None:
        """Score `generator` and append one row per (set, metric) to the CSV at `path`."""
        scores = self.score(generator)
        path.parent.mkdir(parents=True, exist_ok=True)
        new = not path.is_file()
        with path.open("a", newline="") as handle:
            writer = csv.DictWriter(handle, CURVE_COLUMNS)
            if new:
                writer.writeheader()
            for (name, metric), value in scores.items():
                writer.writerow({"step": step, "samples_seen": samples_seen, "set": name, "metric": metric,
                                 "network": f"{value:.6g}", "baseline": f"{self.baseline[(name, metric)]:.6g}"})

    def _scores(self, upsample: Callable[[np.ndarray], np.ndarray],
                generator: Generator | None) -> dict[tuple[str, str], float]:
        scores: dict[tuple[str, str], float] = {}
        for name, cases in self.mesh_sets.items():
            per_case = []
            for case, truth in cases:
                output = upsample_by_clusters(case.inputs, upsample)
                per_case.append((chamfer_distance(output, truth), hausdorff_distance(output, truth),
                                 float(point_to_surface(output, case.mesh.vertices, case.mesh.triangles).mean())))
            scores.update({(name, metric): float(v) for metric, v in zip(MESH_METRICS, np.mean(per_case, axis=0))})
        for name, pairs in self.street_sets.items():
            # a generator's street outputs are drawn from their own seeded source, as before the
            # snapped metric (the recorded curves' values stay comparable)
            outputs = generated(generator, pairs.inputs) if generator is not None else upsample(pairs.inputs)
            scores[(name, "CD")] = float(np.mean(pair_chamfers(outputs, pairs.truth)))
            scores[(name, "snapped CD")] = snapped_chamfers(outputs, pairs)
        return scores

    @property
    def streets(self) -> PatchSet | None:
        """The held-out urban street pairs (set "streets"), or None."""
        return self.street_sets.get(street_set_name("urban"))


def street_set_name(scene_type: str) -> str:
    """The curves' set of held-out streets of a scene type: "streets" for urban (the only type of
    the runs before scene types), "streets-TYPE" for the others."""
    return "streets" if scene_type == "urban" else f"streets-{scene_type}"


def _truth(case: TestCase) -> np.ndarray:
    return sample_surface(case.mesh, SURFACE_SAMPLES, np.random.default_rng(0))[0]


def read_curves(path: Path) -> list[dict[str, str]]:
    """The rows of a curves CSV (empty when the file is missing)."""
    return list(csv.DictReader(Path(path).open())) if Path(path).is_file() else []


def plot_curves(csv_path: Path, png_path: Path) -> Path:
    """One panel per (set, metric): the network's score against samples seen, the baseline's as a
    dashed line. Returns `png_path`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = read_curves(csv_path)
    if not rows:
        raise ValueError(f"{csv_path}: no curve rows to plot")
    panels = list(dict.fromkeys((r["set"], r["metric"]) for r in rows))
    figure, axes = plt.subplots(1, len(panels), figsize=(3.4 * len(panels), 3.0), squeeze=False)
    for axis, (name, metric) in zip(axes[0], panels):
        mine = sorted((int(r["samples_seen"]), float(r["network"]), float(r["baseline"]))
                      for r in rows if (r["set"], r["metric"]) == (name, metric))
        samples, network, base = (np.array(column) for column in zip(*mine))
        axis.plot(samples, network, marker="o", label="CAD-PU")
        axis.axhline(base[-1], color="grey", linestyle="--", label="midpoint baseline")
        axis.set_title(f"{name}: {metric}")
        axis.set_xlabel("patch samples seen")
    axes[0][0].legend()
    figure.tight_layout()
    png_path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(png_path, dpi=80)
    plt.close(figure)
    return png_path


def score_snapshots(snapshots: Path, curves: HeldoutCurves, csv_path: Path, start: str | None = None) -> int:
    """Score a run's generator snapshots (`Recipe.snapshot_every`: step-NNNNNNN.pt) and append their
    rows to `csv_path`, as `curves_every` would have during the run (for runs on a machine that
    cannot compute the curves, e.g. without Open3D). `start`: the weights the run started from
    (name or path), scored as step 0. Returns the number of generators scored."""
    from .train import samples_seen
    from .weights import load_generator

    sources = ([start] if start else []) + sorted(str(path) for path in Path(snapshots).glob("step-*.pt"))
    if not sources:
        raise ValueError(f"{snapshots}: no step-*.pt snapshots")
    for index, source in enumerate(sources):
        generator, _, meta = load_generator(source)
        step = 0 if start and index == 0 else int(meta.get("steps", 0))
        curves.record(generator, step, samples_seen(meta), csv_path)
    return len(sources)


def _arguments_problem(csv_path: Path, png_path: Path, scoring: bool) -> str | None:
    """What is wrong with the command line's CSV and PNG paths, or None: the CSV must exist with the
    curve columns (unless snapshots are scored into it), the PNG must end in .png and not be a folder."""
    if png_path.suffix.lower() != ".png" or png_path.is_dir():
        return f"{png_path}: give a .png file to draw the curves into"
    if csv_path.is_dir():
        return f"{csv_path} is a folder, not a curves CSV"
    if not csv_path.is_file():
        return None if scoring else f"{csv_path} does not exist (a run's curves CSV: recipe curves_csv)"
    with csv_path.open(newline="") as handle:
        header = next(csv.reader(handle), [])
    missing = [column for column in CURVE_COLUMNS if column not in header]
    return f"{csv_path} is not a curves CSV: no column {', '.join(missing)}" if missing else None


def main(argv: list[str] | None = None) -> None:
    """CLI: python -m cadpu.curves CSV PNG [--score-snapshots DIR ...]: plot a run's held-out curves,
    after scoring its snapshots into CSV when asked."""
    parser = argparse.ArgumentParser(description="Plot a training run's held-out learning curves.")
    parser.add_argument("csv", type=Path)
    parser.add_argument("png", type=Path)
    parser.add_argument("--score-snapshots", type=Path, default=None, metavar="DIR",
                        help="score the step-*.pt generators in DIR first, appending to CSV")
    parser.add_argument("--start", default=None, help="with --score-snapshots: the run's starting weights, as step 0")
    parser.add_argument("--meshes", type=int, default=20, help="held-out procedural meshes")
    parser.add_argument("--streets", type=int, default=2, help="held-out simulated streets (0: none)")
    parser.add_argument("--vertical-scale", type=float, default=1.0, help="the recipe's data.scan_vertical_scale")
    parser.add_argument("--sensor", default="measured", help="the recipe's data.sensor")
    parser.add_argument("--pugan", type=Path, default=None, help="folder of the PU-GAN test meshes")
    parser.add_argument("--scene-types", default="urban", help="the recipe's data.scene_types, comma-separated")
    args = parser.parse_args(argv)
    problem = _arguments_problem(args.csv, args.png, args.score_snapshots is not None)
    if problem:  # said before any scoring, in one line (tracebacks, exit 1, before)
        parser.exit(2, f"cadpu.curves: {problem}\n")
    if args.score_snapshots is not None:
        curves = HeldoutCurves(args.meshes, args.streets, args.vertical_scale, args.pugan, args.sensor,
                               tuple(args.scene_types.split(",")))
        print(f"scored {score_snapshots(args.score_snapshots, curves, args.csv, args.start)} generators into {args.csv}")
    print(plot_curves(args.csv, args.png))


if __name__ == "__main__":
    main()
