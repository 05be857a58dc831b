"""The 16-to-64-beam evaluation on real KITTI scans (issue 5): how much a method recovers of the
rings it never saw. `kitti-pu eval-kitti` runs `evaluate_kitti`.

For each scan (any drive, sequence or `.bin` folder that `stages.load.discover` finds):

1. the scan's 64 rings are recovered from the point order (`stages.rings.recover_rings`) and rings
   0, 4, 8, ... are kept: a 16-beam input (`methods.thin_scan`);
2. the input is densified 4x, side by side, by every method of `methods.COMPARED_METHODS` (the input
   itself, range-image interpolation, the midpoint baseline and the two CAD-PU weight files; the
   last three through the pipeline's own chain, settings from a `PipelineConfig`);
3. each output is scored against the full 64-ring scan (`scoring.Reference`), on the whole scan
   and on its non-ground region, with the metrics of `cadpu.metrics`;
4. the rows and their means are printed and written as CSV (`report`), the first scan drawn as a
   PNG (`figure`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from cadpu.weights import resolve as resolve_weights
from stages import ground, load
from stages.discovery import scans_among
from stages.errors import InputError
from stages.upsample import PatchUpsampler

from ..chain import tool_version
from ..config import ConfigError, PipelineConfig
from ..preflight import check_output_target
from .figure import ScanOutputs, render_figure
from .methods import NETWORK, load_models, method_outputs, thin_scan
from .report import format_table, per_scan_comparison, write_csv, write_record
from .scoring import NON_GROUND, VOXEL_SIZE, Reference, Row, mean_rows

#: The evaluation's ring step and upsampling ratio: every 4th of 64 rings in, densified 4x.
RATIO = 4


def _meta_values(models: dict[str, PatchUpsampler], key: str) -> set[str]:
    """What either model's meta lists under `key` (`kitti-pu finetune`'s records)."""
    return {value for model in models.values() for value in (getattr(model, "meta", None) or {}).get(key, [])}


def _scans_trained_on(refs: list[load.FrameRef], models: dict[str, PatchUpsampler],
                      digest_of: dict[str, str] | None = None) -> list[str]:
    """The scans of `refs` that either model was fine-tuned on (`kitti-pu finetune` records them in
    the weights' meta as finetune_scans and finetune_scan_digests), by resolved path or by content
    (a copy elsewhere). `digest_of`: see `stages.discovery.scans_among`."""
    return list(scans_among([ref.source for ref in refs], _meta_values(models, "finetune_scans"),
                            _meta_values(models, "finetune_scan_digests"), digest_of))


def _scans_that_chose(refs: list[load.FrameRef], models: dict[str, PatchUpsampler],
                      digest_of: dict[str, str] | None = None) -> list[str]:
    """The scans of `refs` that chose either model's weights when it was fine-tuned (the meta's
    finetune_heldout_scans by resolved path, finetune_heldout_digests by content): scored to pick
    the best step, so their scores are not held-out scores either."""
    return list(scans_among([ref.source for ref in refs], _meta_values(models, "finetune_heldout_scans"),
                            _meta_values(models, "finetune_heldout_digests"), digest_of))


@dataclass(frozen=True)
class EvalResult:
    """What `evaluate_kitti` produced: every row (per scan, then the means), the printed table
    (`format_table`, then `per_scan_comparison`), and the CSV and PNG written."""

    rows: list[Row]
    table: str
    csv_path: Path
    png_path: Path | None
    #: eval_kitti.json: the input, weights (with checksums), settings and version that made the CSV
    record_path: Path
    #: {method: the weights file it ran, with its checksum} for the two CAD-PU rows
    weights: dict[str, str]
    #: one line per scan that could not be evaluated (the file and why); the others are scored
    failed: list[str]


def evaluate_scan(points: np.ndarray, key: str, models: dict[str, PatchUpsampler], config: PipelineConfig,
                  source: str = "", voxel: float = VOXEL_SIZE) -> tuple[list[Row], ScanOutputs]:
    """Thin one full scan to 16 rings, densify it with every method and score each output.

    Args:
        points: (N, 4) full 64-ring scan in KITTI order, sensor frame, metres.
        key: the scan's name in the table. models: learned methods by name (see `method_outputs`).
        config: pipeline settings (its ground method also labels the full scan). source: file name
        for errors. voxel: occupancy voxel edge, metres.

    Returns:
        Rows (method x region, in `COMPARED_METHODS` x `REGIONS` order) and the clouds for the figure.
    """
    ratio = config.upsample.ratio
    thinned, rings = thin_scan(points, source, ratio=ratio)
    full_ground = ground.segment(points, config.ground.method, config.ground.method_params()).mask
    reference = Reference(points, full_ground, voxel)
    limits = config.input  # as the full scan was read: other limits dropped points `rings` still counted
    frame = load.frame_from_points(thinned, dataset="eval", sequence="eval", source=source or key,
                                   max_range=limits.max_range, min_range=limits.min_range,
                                   max_out_of_range_share=limits.max_out_of_range_share)
    outputs = method_outputs(frame, rings, models, config, ratio=ratio)
    rows = [Row(key, method, region, score, seconds)
            for method, (cloud, seconds) in outputs.items()
            for region, score in reference.score(cloud).items()]
    clouds = ScanOutputs(key, points[:, :3], full_ground, thinned[:, :3],
                         {method: cloud for method, (cloud, _) in outputs.items()})
    return rows, clouds


def evaluate_kitti(path: str | Path, out_dir: str | Path, weights: str | Path | None = None,
                   twin_weights: str | Path | None = None, frames: int | None = None,
                   config: PipelineConfig | None = None, voxel: float = VOXEL_SIZE,
                   log: Callable[[str], None] | None = None) -> EvalResult:
    """Run the 16-to-64-beam evaluation on every scan under `path`.

    Args:
        path: a KITTI raw drive, odometry sequence, folder of .bin scans, or a base folder
            (`stages.load.discover`).
        out_dir: where `eval_kitti.csv` and `eval_kitti.png` (the first scan) are written.
        weights, twin_weights: the CAD-PU weights under test and their twin (None: see `load_models`).
        frames: evaluate only the first `frames` scans (None = all) of those selected.
        config: pipeline settings (every stage's from ground to fill, as `kitti-pu run` uses them,
            and the upsample section's model settings; `input`'s kind, sequences, frame range and
            range limits select and read the scans, its path is not used); None = defaults.
            `upsample.ratio` must be `RATIO` (4: 64 -> 16 rings -> 4x).
        voxel: occupancy voxel edge, metres.
        log: called with one line per scan as it is done (e.g. `print`).

    Returns:
        The `EvalResult`: rows per scan and the means, the table, the paths written.

    A scan that cannot be evaluated (a bad file, not a full scan in KITTI order) is left out and
    listed in `EvalResult.failed`; the others are scored.

    Raises:
        InputError: nothing to evaluate under `path`, no scan could be evaluated, a ratio other than
            `RATIO`, or `out_dir` cannot be written (a file there or on the way, a read-only place).
        cadpu.weights.WeightsError: a missing or corrupt weights file.
    """
    config = config or PipelineConfig()
    if frames is not None and frames < 1:
        raise InputError("eval-kitti", str(path), f"--frames must be at least 1, got {frames}")
    if config.upsample.ratio != RATIO:  # the rows, the figure and the scoring say 16 rings in, 64 out
        raise InputError("eval-kitti", str(path), f"upsample.ratio must be {RATIO} here (64 rings thinned to 16, "
                                                  f"densified 4x), got {config.upsample.ratio}")
    out_dir = Path(out_dir)
    try:  # found now, not after a scan is scored: a file there, or on the way, or a read-only place
        check_output_target(out_dir, "--out")
    except ConfigError as error:
        raise InputError("eval-kitti", str(out_dir), str(error)) from None
    section = config.input
    refs = load.discover(path, section.kind, section.sequences, section.frame_range())[:frames]
    if not refs:
        raise InputError("eval-kitti", str(path), "no scans found")
    models, files = load_models(weights, twin_weights, config)
    tested_weights = resolve_weights(weights or config.upsample.weights).resolve()
    digest_of: dict[str, str] = {}  # each scan hashed once for both
    trained_on = _scans_trained_on(refs, models, digest_of)
    chose = [scan for scan in _scans_that_chose(refs, models, digest_of) if scan not in trained_on]
    if trained_on and log is not None:
        log(f"eval-kitti: warning: {len(trained_on)} of the {len(refs)} scans are scans the weights were fine-tuned on "
            f"(their meta's finetune_scans), e.g. {trained_on[0]}: their scores are not held-out scores")
    if chose and log is not None:
        log(f"eval-kitti: warning: {len(chose)} of the {len(refs)} scans chose the weights when they were fine-tuned "
            f"(their meta's finetune_heldout_scans), e.g. {chose[0]}: their scores are not held-out scores")
    rows: list[Row] = []
    png_path: Path | None = None
    failed: list[str] = []
    for ref in refs:
        try:
            points = load.scan_points(ref.source, config.input)
            scan_rows, clouds = evaluate_scan(points, ref.key, models, config, ref.source, voxel)
        except InputError as error:  # a bad scan is reported and left out; the others are scored
            failed.append(str(error))
            if log is not None:
                log(f"{ref.key}: not evaluated: {error}")
            continue
        rows += scan_rows
        if png_path is None:
            png_path = render_figure(clouds, out_dir / "eval_kitti.png")
        if log is not None:
            tested = next((r for r in scan_rows if r.method == NETWORK and r.region == NON_GROUND), None)
            summary = f" {NETWORK} non-ground CD {tested.score.chamfer:.4f} m, F1 {tested.score.f1:.3f}" \
                if tested else ""
            log(f"{ref.key}: {len(points):,} points;{summary}")
    if not rows:
        raise InputError("eval-kitti", str(path), f"no scan could be evaluated ({len(failed)} tried; the first: "
                                                  f"{failed[0]})")
    rows += mean_rows(rows)
    csv_path = write_csv(rows, out_dir / "eval_kitti.csv")
    # the CSV alone did not say which weights and settings made it (a trial)
    # the settings as they ran: `--weights` in upsample.weights (the default's name was recorded
    # beside the weights that ran, a trial)
    ran = config.model_copy(update={"upsample": config.upsample.model_copy(update={"weights": str(tested_weights)})})
    record_path = write_record({"input": str(Path(path).resolve()), "weights": files,
                                "weights_sha256": {method: model.checksum for method, model in models.items()},
                                "voxel_m": voxel,
                                "scans": sorted({row.scan for row in rows} - {"mean"}), "not_evaluated": failed,
                                # scores that are not held-out ones (the record had no trace of them: a trial)
                                "fine_tuned_on": trained_on, "chose_the_weights": chose,
                                "config": ran.model_dump(mode="json"), "config_hash": ran.output_hash(),
                                "tool_version": tool_version()}, out_dir / "eval_kitti.json")
    described = "\n".join(f"{method}: {file}" for method, file in files.items())
    warning = "\n".join(line for line in (
        f"warning: {len(trained_on)} of these scans trained the fine-tuned weights: not held-out scores"
        if trained_on else "",
        f"warning: {len(chose)} of these scans chose the fine-tuned weights: not held-out scores" if chose else "")
        if line)
    table = "\n\n".join(part for part in (described, warning, format_table(rows, voxel), per_scan_comparison(rows))
                        if part)
    return EvalResult(rows=rows, table=table, csv_path=csv_path, png_path=png_path, record_path=record_path,
                      weights=files, failed=failed)
