"""The 16-to-64-beam evaluation on real KITTI scans (issue 5): how much a method recovers of the
rings it never saw.

For each scan (any drive, sequence or `.bin` folder that `stages.load.discover` finds):

1. the scan's 64 rings are recovered from the point order (`stages.rings.recover_rings`) and rings
   0, 4, 8, ... are kept: a 16-beam input;
2. the input is densified 4x, side by side, by every method of `METHODS`:
   - "16-ring input": the input as it is (the floor);
   - "range-image linear": new rings interpolated in the range image (`stages.range_image`), the
     standard LiDAR super-resolution baseline; it densifies ground and objects alike;
   - "midpoint baseline": the non-learned `cadpu.baseline` on the pipeline's patches;
   - "CAD-PU alpha 1.0" and "CAD-PU (shipped)": the two weight files;
   the last three run the pipeline's own stages in this process (ground -> tile -> upsample ->
   stitch, settings from a `PipelineConfig`), so they see the 16-ring input exactly as
   `kitti-pu run` would;
3. each output is scored against the full 64-ring scan (`Reference`), on the whole scan and on
   its non-ground region.

The non-ground region: the ground of the FULL scan is found once (`stages.ground.segment` with the
configured method); the reference region is the full scan's non-ground points, and an output
point belongs to the region when its nearest full-scan point is non-ground. So every method is
cut by the same, denser and more reliable ground mask, whatever its own ground flags (the range
image baseline has none), and ground removal errors on the thinned input do not hide in the score.

Metrics (metres, and fractions of occupied voxels): Chamfer distance (mean of the two directed
mean nearest-neighbour distances), Hausdorff (larger directed maximum) and HD95 (larger directed
95th percentile), the same definitions as `cadpu.metrics`; precision, recall and F1 of occupied
`voxel` cubes (`cadpu.metrics.voxel_f1`).
"""

from __future__ import annotations

import csv
import math
import time
from collections.abc import Callable, Iterable
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np
from scipy.spatial import cKDTree

from cadpu.baseline import upsample_patches as midpoint_patches
from cadpu.metrics import directed_distances, voxel_f1
from stages.range_image import interpolate_rings
from stages import ground, load
from stages.rings import keep_rings, recover_rings
from stages.errors import InputError
from stages.frame import Frame
from stages.upsample import PatchUpsampler

from .chain import Chain
from .config import PipelineConfig

INPUT = "16-ring input"
RANGE_IMAGE = "range-image linear"
MIDPOINT = "midpoint baseline"
UNIFORM = "CAD-PU alpha 1.0"
SHIPPED = "CAD-PU (shipped)"
#: The methods compared, in table order.
METHODS = (INPUT, RANGE_IMAGE, MIDPOINT, UNIFORM, SHIPPED)
NON_GROUND = "non-ground"
WHOLE = "whole"
REGIONS = (NON_GROUND, WHOLE)
#: Keep one ring in this many (64 -> 16), and upsample by the same ratio.
RING_STEP = 4
#: Edge of the occupancy voxels, metres.
VOXEL_SIZE = 0.1
#: Half width of the bird's-eye crop of the figure, metres (a 40 x 40 m square round the sensor).
FIGURE_HALF_WIDTH = 20.0
MAX_PLOTTED = 120_000


@dataclass(frozen=True)
class Score:
    """How close one output is to the full scan in one region.

    Attributes:
        points: output points in the region.
        chamfer, hausdorff, hd95: metres (NaN when the output or the reference region is empty).
        precision, recall, f1: occupied-voxel agreement, fractions in [0, 1].
    """

    points: int
    chamfer: float
    hausdorff: float
    hd95: float
    precision: float
    recall: float
    f1: float


@dataclass(frozen=True)
class Row:
    """One line of the result table: a method's score on one scan ("mean" for the average) and
    region, and the seconds the method took on that scan (densification only, not scoring)."""

    scan: str
    method: str
    region: str
    score: Score
    seconds: float

    def as_dict(self) -> dict[str, object]:
        """Flat {column: value} for the CSV."""
        return {"scan": self.scan, "method": self.method, "region": self.region, **asdict(self.score),
                "seconds": self.seconds}


@dataclass(frozen=True)
class ScanOutputs:
    """One scan's clouds, kept for the figure: full (N, 3), its ground mask (N,), the 16-ring input
    (M, 3) and every method's output (Q, 3), all sensor frame, metres."""

    key: str
    full: np.ndarray
    full_ground: np.ndarray
    input: np.ndarray
    outputs: dict[str, np.ndarray]


@dataclass(frozen=True)
class EvalResult:
    """What `evaluate_kitti` produced: every row (per scan, then the means), the printed table
    (`format_table`, then `per_scan_comparison`), and the CSV and PNG written."""

    rows: list[Row]
    table: str
    csv_path: Path
    png_path: Path | None


class MidpointUpsampler:
    """The non-learned baseline (`cadpu.baseline.upsample_patches`) behind the interface
    `stages.upsample.run` expects of a model (`PatchUpsampler`).

    Its output holds each patch's input points besides the new ones, so without ring snapping its
    stitched cloud is built without re-adding the input (`keep_input=False`). With ring snapping
    those copies are generated points like a network's and move to virtual rings, so the input is
    re-added, as for the networks (`midpoint_keeps_input`).
    """

    def __init__(self, ratio: int = RING_STEP) -> None:
        self.ratio = ratio

    def upsample_patches(self, patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """(B, K, 3) normalised patches -> (B, K*r, 3) float32 points and (B, K*r) int64 parent slots."""
        if len(patches) == 0:
            k = patches.shape[1] * self.ratio if patches.ndim == 3 else 0
            return np.zeros((0, k, 3), np.float32), np.zeros((0, k), np.int64)
        return midpoint_patches(np.asarray(patches, dtype=np.float64), self.ratio)


class Reference:
    """The full 64-ring scan as the yardstick: scores any output against it in both regions.

    Args:
        full: (N, 3+) full scan, sensor frame, metres.
        full_ground: (N,) bool ground mask of the full scan.
        voxel: occupancy voxel edge, metres.
    """

    def __init__(self, full: np.ndarray, full_ground: np.ndarray, voxel: float = VOXEL_SIZE) -> None:
        self.xyz = np.asarray(full, dtype=np.float64)[:, :3]
        self.ground = np.asarray(full_ground, dtype=bool)
        if self.ground.shape != (len(self.xyz),):
            raise ValueError(f"Reference: {len(self.xyz)} points but a ground mask of shape {self.ground.shape}")
        self.voxel = voxel
        self._tree = cKDTree(self.xyz)
        non_ground = self.xyz[~self.ground]
        self._non_ground = non_ground
        self._non_ground_tree = cKDTree(non_ground) if len(non_ground) else None

    def score(self, predicted: np.ndarray) -> dict[str, Score]:
        """Score an output cloud.

        Args:
            predicted: (Q, 3+) output points, sensor frame, metres.

        Returns:
            {"non-ground": Score, "whole": Score}; an output point is in the non-ground region when
            its nearest full-scan point is non-ground.
        """
        xyz = np.asarray(predicted, dtype=np.float64)[:, :3]
        if len(xyz) == 0:
            return {region: _empty_score() for region in REGIONS}
        to_full, nearest = self._tree.query(xyz, k=1, workers=-1)
        in_region = ~self.ground[nearest]
        whole = _score(xyz, self.xyz, to_full, self.voxel)
        if self._non_ground_tree is None or not in_region.any():
            return {NON_GROUND: _empty_score(int(in_region.sum())), WHOLE: whole}
        region_xyz = xyz[in_region]
        to_region, _ = self._non_ground_tree.query(region_xyz, k=1, workers=-1)
        return {NON_GROUND: _score(region_xyz, self._non_ground, to_region, self.voxel), WHOLE: whole}


def _empty_score(points: int = 0) -> Score:
    return Score(points, math.nan, math.nan, math.nan, 0.0, 0.0, 0.0)


def _score(predicted: np.ndarray, reference: np.ndarray, to_reference: np.ndarray, voxel: float) -> Score:
    """Score of (Q, 3) predicted points against (N, 3) reference points, given the (Q,) distances
    of the predicted points to the reference (already computed for the region split)."""
    from_reference = directed_distances(reference, predicted)
    voxels = voxel_f1(predicted, reference, voxel)
    return Score(points=len(predicted),
                 chamfer=float(0.5 * (to_reference.mean() + from_reference.mean())),
                 hausdorff=float(max(to_reference.max(), from_reference.max())),
                 hd95=float(max(np.percentile(to_reference, 95), np.percentile(from_reference, 95))),
                 precision=voxels.precision, recall=voxels.recall, f1=voxels.f1)


def thin_scan(points: np.ndarray, source: str = "", every: int = RING_STEP) -> tuple[np.ndarray, np.ndarray]:
    """The scan's rings 0, every, 2 * every, ... (the 16-beam input of a 64-beam scan).

    Args:
        points: (N, 4) scan in KITTI point order. source: file name for errors.

    Returns:
        (M, 4) kept points in their original order and (M,) int64 their ring ids in the full scan
        (0, every, 2 * every, ...).

    Raises:
        InputError: the point order shows fewer than 2 * `every` rings (not a KITTI-ordered scan).
    """
    rings = recover_rings(points)
    count = int(rings.max()) + 1 if len(rings) else 0
    if count < 2 * every:
        raise InputError("eval-kitti", source, f"only {count} laser rings found in the point order; the "
                                               "16-to-64-beam evaluation needs a scan in KITTI order")
    return keep_rings(points, rings, every=every), keep_rings(rings, rings, every=every)


def densify_with_pipeline(frame: Frame, upsampler: PatchUpsampler, config: PipelineConfig,
                          keep_input: bool | None = None) -> np.ndarray:
    """The pipeline's chain in this process, without writing: ground -> tile -> upsample -> stitch
    -> snap -> fill, with `config`'s settings and `upsampler` as the model.

    Args:
        frame: a frame with `points` (N, 4), sensor frame, and its `rings` (`load.frame_from_points`).
        upsampler: the model (`cadpu.inference.Upsampler`, `MidpointUpsampler`, ...).
        config: the pipeline settings.
        keep_input: override of `config.stitch.keep_input` (None keeps the configured value).

    Returns:
        (Q, 3) float32 output cloud, sensor frame, metres (ground points included as configured).
    """
    if keep_input is not None:
        config = config.model_copy(update={"stitch": config.stitch.model_copy(update={"keep_input": keep_input})})
    return Chain(config, upsampler=upsampler, writes=False).run(frame).cloud.xyz


def midpoint_keeps_input(config: PipelineConfig) -> bool:
    """Whether the midpoint baseline's stitched cloud re-adds the input points: only when its own
    copies of them are moved away by ring snapping (see `MidpointUpsampler`)."""
    return config.snap.enabled and config.stitch.keep_input


def method_outputs(frame: Frame, rings: np.ndarray, models: dict[str, PatchUpsampler], config: PipelineConfig,
                   every: int = RING_STEP) -> dict[str, tuple[np.ndarray, float]]:
    """Every method's densification of one 16-ring frame.

    Args:
        frame: the thinned scan (`thin_scan`) as a frame. rings: (M,) ring id of each of its points.
        models: the learned methods by name (e.g. {UNIFORM: ..., SHIPPED: ...}).
        config: pipeline settings. every: the ring step the input was thinned by (= the ratio).

    Returns:
        {method: ((Q, 3) float32 cloud in the sensor frame, seconds taken)} in `METHODS` order
        (methods missing from `models` are left out).
    """
    results: dict[str, tuple[np.ndarray, float]] = {INPUT: (frame.points[:, :3], 0.0)}
    started = time.perf_counter()
    dense = interpolate_rings(frame.points, rings, factor=every)
    results[RANGE_IMAGE] = (dense[:, :3], time.perf_counter() - started)
    started = time.perf_counter()
    results[MIDPOINT] = (densify_with_pipeline(frame, MidpointUpsampler(every), config,
                                               keep_input=midpoint_keeps_input(config)),
                         time.perf_counter() - started)
    for name in METHODS:
        if name in models:
            started = time.perf_counter()
            results[name] = (densify_with_pipeline(frame, models[name], config), time.perf_counter() - started)
    return results


def evaluate_scan(points: np.ndarray, key: str, models: dict[str, PatchUpsampler], config: PipelineConfig,
                  source: str = "", voxel: float = VOXEL_SIZE) -> tuple[list[Row], ScanOutputs]:
    """Thin one full scan to 16 rings, densify it with every method and score each output.

    Args:
        points: (N, 4) full 64-ring scan in KITTI order, sensor frame, metres.
        key: the scan's name in the table. models: learned methods by name (see `method_outputs`).
        config: pipeline settings (its ground method also labels the full scan). source: file name
        for errors. voxel: occupancy voxel edge, metres.

    Returns:
        Rows (method x region, in `METHODS` x `REGIONS` order) and the clouds for the figure.
    """
    ratio = config.upsample.ratio
    thinned, rings = thin_scan(points, source, every=ratio)
    full_ground = ground.segment(points, config.ground.method, config.ground.method_params()).mask
    reference = Reference(points, full_ground, voxel)
    frame = load.frame_from_points(thinned, dataset="eval", sequence="eval", source=source or key)
    outputs = method_outputs(frame, rings, models, config, every=ratio)
    rows = [Row(key, method, region, score, seconds)
            for method, (cloud, seconds) in outputs.items()
            for region, score in reference.score(cloud).items()]
    clouds = ScanOutputs(key, points[:, :3], full_ground, thinned[:, :3],
                         {method: cloud for method, (cloud, _) in outputs.items()})
    return rows, clouds


def mean_rows(rows: Iterable[Row]) -> list[Row]:
    """One "mean" row per (method, region): the average of each metric over the scans (NaN
    distances are left out of the averages; point counts are rounded)."""
    groups: dict[tuple[str, str], list[Row]] = {}
    for row in rows:
        groups.setdefault((row.method, row.region), []).append(row)
    means = []
    for (method, region), group in groups.items():
        values = {name: [getattr(r.score, name) for r in group] for name in Score.__dataclass_fields__}
        averaged = {name: _nanmean(column) for name, column in values.items()}
        averaged["points"] = int(round(averaged["points"]))
        means.append(Row("mean", method, region, Score(**averaged), _nanmean([r.seconds for r in group])))
    return means


def _nanmean(values: list[float]) -> float:
    finite = [v for v in values if not math.isnan(v)]
    return float(np.mean(finite)) if finite else math.nan


def format_table(rows: list[Row], voxel: float = VOXEL_SIZE) -> str:
    """A plain-text table per region: scan, method, points, CD, HD, HD95 (metres), P, R, F1 (of
    occupied `voxel`-metre cubes)."""
    header = f"{'scan':<24} {'method':<20} {'points':>8} {'CD m':>8} {'HD m':>8} {'HD95 m':>8} " \
             f"{'P':>6} {'R':>6} {'F1':>6}"
    blocks = []
    for region in REGIONS:
        lines = [f"{region} region (vs the full 64-ring scan, voxels {voxel} m)", header, "-" * len(header)]
        for row in (r for r in rows if r.region == region):
            s = row.score
            lines.append(f"{row.scan:<24} {row.method:<20} {s.points:>8d} {s.chamfer:>8.4f} {s.hausdorff:>8.3f} "
                         f"{s.hd95:>8.3f} {s.precision:>6.3f} {s.recall:>6.3f} {s.f1:>6.3f}")
        blocks.append("\n".join(lines))
    return "\n\n".join(blocks)


def per_scan_comparison(rows: list[Row], method: str = SHIPPED, region: str = NON_GROUND) -> str:
    """On how many scans `method` beats each other method in `region`: lower Chamfer distance,
    higher voxel F1 (ties and NaN count as not better). The "mean" rows are left out.

    Returns:
        One line per other method, e.g. "  range-image linear   CD lower on 6/6   F1 higher on 4/6",
        under a heading; "" when `method` has no per-scan rows in `region`.
    """
    scores = {(r.scan, r.method): r.score for r in rows if r.region == region and r.scan != "mean"}
    scans = [scan for scan, name in scores if name == method]
    if not scans:
        return ""
    lines = [f"{method} against each method, {region} region, per scan"]
    for other in dict.fromkeys(name for _, name in scores if name != method):
        pairs = [(scores[scan, method], scores[scan, other]) for scan in scans if (scan, other) in scores]
        lower = sum(ours.chamfer < theirs.chamfer for ours, theirs in pairs)
        higher = sum(ours.f1 > theirs.f1 for ours, theirs in pairs)
        lines.append(f"  {other:<20} CD lower on {lower}/{len(pairs)}   F1 higher on {higher}/{len(pairs)}")
    return "\n".join(lines)


def write_csv(rows: list[Row], path: Path) -> Path:
    """Write the rows as CSV (columns: scan, method, region, points, chamfer, hausdorff, hd95,
    precision, recall, f1, seconds); returns `path`."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    temporary = path.with_name(f".{path.name}.tmp")
    with temporary.open("w", newline="") as handle:
        writer = csv.DictWriter(handle, fieldnames=list(rows[0].as_dict()) if rows else ["scan"])
        writer.writeheader()
        writer.writerows(row.as_dict() for row in rows)
    temporary.replace(path)
    return path


def render_figure(clouds: ScanOutputs, path: Path, methods: tuple[str, ...] = (RANGE_IMAGE, MIDPOINT, SHIPPED),
                  half_width: float = FIGURE_HALF_WIDTH) -> Path:
    """PNG of one scan: the 16-ring input, the outputs of `methods` and the full 64-ring scan.

    Top row: bird's-eye view of a 2 * half_width square round the sensor, coloured by height.
    Bottom row: front view (azimuth within +-45 degrees of straight ahead against elevation, left
    on the left), coloured by log range, which shows the rings each method adds.

    Returns:
        `path`.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    panels = [(INPUT, clouds.input)] + [(m, clouds.outputs[m]) for m in methods if m in clouds.outputs]
    panels.append(("full 64-ring scan", clouds.full))
    figure, axes = plt.subplots(2, len(panels), figsize=(5.2 * len(panels), 9.5), dpi=110, squeeze=False)
    for column, (label, cloud) in enumerate(panels):
        _bird_eye(axes[0, column], np.asarray(cloud, dtype=np.float64), half_width, f"{label}\n{len(cloud):,} points")
        _front_view(axes[1, column], np.asarray(cloud, dtype=np.float64))
    figure.suptitle(f"16-to-64-beam evaluation: {clouds.key}")
    figure.tight_layout()
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    figure.savefig(path)
    plt.close(figure)
    return path


def _subsample(cloud: np.ndarray) -> np.ndarray:
    if len(cloud) <= MAX_PLOTTED:
        return cloud
    return cloud[np.random.default_rng(0).choice(len(cloud), MAX_PLOTTED, replace=False)]


def _bird_eye(axis, cloud: np.ndarray, half_width: float, title: str) -> None:
    inside = (np.abs(cloud[:, 0]) < half_width) & (np.abs(cloud[:, 1]) < half_width)
    crop = _subsample(cloud[inside])
    axis.scatter(crop[:, 0], crop[:, 1], s=0.08, c=crop[:, 2], cmap="viridis", vmin=-2.0, vmax=2.0, linewidths=0)
    axis.set_xlim(-half_width, half_width)
    axis.set_ylim(-half_width, half_width)
    axis.set_aspect("equal")
    axis.set_title(title)
    axis.set_xlabel("x (m, forward)")
    axis.set_ylabel("y (m, left)")


def _front_view(axis, cloud: np.ndarray) -> None:
    distance = np.linalg.norm(cloud[:, :3], axis=1)
    azimuth = np.degrees(np.arctan2(cloud[:, 1], cloud[:, 0]))
    elevation = np.degrees(np.arcsin(np.clip(cloud[:, 2] / np.maximum(distance, 1e-9), -1.0, 1.0)))
    ahead = np.abs(azimuth) < 45.0
    points = _subsample(np.column_stack([-azimuth[ahead], elevation[ahead], distance[ahead]]))
    axis.scatter(points[:, 0], points[:, 1], s=0.3, c=np.log(np.maximum(points[:, 2], 1.0)), cmap="turbo",
                 vmin=np.log(2.0), vmax=np.log(60.0), linewidths=0)
    axis.set_xlim(-45.0, 45.0)
    axis.set_ylim(-26.0, 4.0)
    axis.set_xlabel("azimuth (deg, left is left)")
    axis.set_ylabel("elevation (deg)")


def load_models(weights: str | Path | None, uniform_weights: str | Path | None,
                config: PipelineConfig) -> dict[str, PatchUpsampler]:
    """The two CAD-PU models: `weights` (None = `config.upsample.weights`, by default the shipped
    cadpu_r4_lidar) and `uniform_weights` (alpha = 1.0; None = the shipped file trained like
    `weights`, `cadpu.weights.uniform_counterpart`).

    Raises:
        cadpu.weights.WeightsError naming a missing or corrupt file.
    """
    from cadpu.inference import Upsampler
    from cadpu.weights import uniform_counterpart

    section = config.upsample
    weights = weights or section.weights
    common = dict(ratio=section.ratio, device=section.device, batch_size=section.batch_size, seed=section.seed)
    return {UNIFORM: Upsampler(uniform_weights or uniform_counterpart(weights), **common),
            SHIPPED: Upsampler(weights, **common)}


def evaluate_kitti(path: str | Path, out_dir: str | Path, weights: str | Path | None = None,
                   uniform_weights: str | Path | None = None, frames: int | None = None,
                   config: PipelineConfig | None = None, voxel: float = VOXEL_SIZE,
                   log: Callable[[str], None] | None = None) -> EvalResult:
    """Run the 16-to-64-beam evaluation on every scan under `path`.

    Args:
        path: a KITTI raw drive, odometry sequence, folder of .bin scans, or a base folder
            (`stages.load.discover`).
        out_dir: where `eval_kitti.csv` and `eval_kitti.png` (the first scan) are written.
        weights, uniform_weights: the CAD-PU and alpha = 1.0 weight files (None: see `load_models`).
        frames: evaluate only the first `frames` scans (None = all).
        config: pipeline settings (ground, tile, stitch, upsample device/seed); None = defaults.
            `upsample.ratio` is the ring step too (4: 64 -> 16 rings -> 4x).
        voxel: occupancy voxel edge, metres.
        log: called with one line per scan as it is done (e.g. `print`).

    Returns:
        The `EvalResult`: rows per scan and the means, the table, the paths written.

    Raises:
        InputError: nothing to evaluate under `path`, or a bad scan (naming the file).
        cadpu.weights.WeightsError: a missing or corrupt weights file.
    """
    config = config or PipelineConfig()
    if frames is not None and frames < 1:
        raise InputError("eval-kitti", str(path), f"--frames must be at least 1, got {frames}")
    refs = load.discover(path)[:frames]
    if not refs:
        raise InputError("eval-kitti", str(path), "no scans found")
    models = load_models(weights, uniform_weights, config)
    out_dir = Path(out_dir)
    rows: list[Row] = []
    png_path: Path | None = None
    for ref in refs:
        points = load.read_scan(ref.source, config.input.max_points)
        scan_rows, clouds = evaluate_scan(points, ref.key, models, config, ref.source, voxel)
        rows += scan_rows
        if png_path is None:
            png_path = render_figure(clouds, out_dir / "eval_kitti.png")
        if log is not None:
            shipped = next((r for r in scan_rows if r.method == SHIPPED and r.region == NON_GROUND), None)
            summary = f" CAD-PU (shipped) non-ground CD {shipped.score.chamfer:.4f} m, F1 {shipped.score.f1:.3f}" \
                if shipped else ""
            log(f"{ref.key}: {len(points):,} points;{summary}")
    rows += mean_rows(rows)
    csv_path = write_csv(rows, out_dir / "eval_kitti.csv")
    table = "\n\n".join(part for part in (format_table(rows, voxel), per_scan_comparison(rows)) if part)
    return EvalResult(rows=rows, table=table, csv_path=csv_path, png_path=png_path)
