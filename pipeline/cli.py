"""`kitti-pu`: the command line, a thin layer over `pipeline` and `cadpu`.

Exit codes: 0 all frames done, 2 bad configuration or input, 3 some frames failed, 1 a crash.
"""

from __future__ import annotations

import sys
from pathlib import Path
from typing import Annotated, Any, Optional

import typer
import yaml

from .config import ConfigError, PipelineConfig, load_config
from .summary import EXIT_BAD_CONFIG

app = typer.Typer(
    add_completion=False,
    no_args_is_help=True,
    help="Densify KITTI LiDAR scans with CAD-PU, on Dask.",
    pretty_exceptions_enable=False,
)

ConfigFiles = Annotated[
    Optional[list[Path]], typer.Option("--config", "-c", help="YAML override file(s), applied in order.")
]
SetOptions = Annotated[
    Optional[list[str]],
    typer.Option("--set", help="Override any key: --set tile.overlap=2.0 (value read as YAML)."),
]


def _parse_sets(items: list[str] | None) -> dict[str, Any]:
    overrides: dict[str, Any] = {}
    for item in items or []:
        key, sep, value = item.partition("=")
        if not sep or not key:
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. --set upsample.ratio=8")
        overrides[key.strip()] = yaml.safe_load(value)
    return overrides


def _fail(message: str, code: int = EXIT_BAD_CONFIG) -> None:
    typer.echo(f"kitti-pu: {message}", err=True)
    raise typer.Exit(code)


def _build_config(files: list[Path] | None, options: dict[str, Any], sets: list[str] | None) -> PipelineConfig:
    try:
        return load_config(files or [], options, _parse_sets(sets))
    except ConfigError as error:
        _fail(str(error))
        raise  # unreachable: _fail exits


@app.command()
def run(
    path: Annotated[Optional[Path], typer.Argument(help="KITTI raw/odometry folder, .bin folder, or a base folder.")] = None,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", help="Output folder.")] = None,
    kind: Annotated[Optional[str], typer.Option(help="auto, raw, odometry or bin.")] = None,
    sequence: Annotated[Optional[list[str]], typer.Option("--sequence", "-s", help="Drive or sequence to take (repeatable).")] = None,
    first: Annotated[Optional[int], typer.Option(help="First frame index.")] = None,
    last: Annotated[Optional[int], typer.Option(help="Last frame index (inclusive).")] = None,
    step: Annotated[Optional[int], typer.Option(help="Take every STEP-th frame.")] = None,
    ratio: Annotated[Optional[int], typer.Option("--ratio", "-r", help="Upsampling ratio (4 is the trained one).")] = None,
    weights: Annotated[Optional[Path], typer.Option(help="Weight file or shipped name (default: cadpu_r4_lidar).")] = None,
    ground: Annotated[Optional[str], typer.Option(help="Ground method: patchwork, ransac, patchworkpp.")] = None,
    scheduler: Annotated[Optional[str], typer.Option(help="Address of an existing Dask scheduler, e.g. tcp://host:8786.")] = None,
    workers: Annotated[Optional[int], typer.Option(help="LocalCluster worker processes.")] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", help="Redo frames whose outputs exist.")] = False,
    dry_run: Annotated[bool, typer.Option("--dry-run", help="Print the resolved configuration and frames, then stop.")] = False,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
    config: ConfigFiles = None,
    set_: SetOptions = None,
) -> None:
    """Densify every frame under PATH and write Parquet/PLY plus a run summary."""
    from .runner import discover_frames, run_pipeline

    options = {
        "input.path": path, "input.kind": kind, "input.sequences": sequence, "input.first_frame": first,
        "input.last_frame": last, "input.step": step, "output.dir": out, "upsample.ratio": ratio,
        "upsample.weights": weights, "ground.method": ground, "dask.scheduler": scheduler,
        "dask.n_workers": workers, "output.overwrite": overwrite or None,
    }
    cfg = _build_config(config, options, set_)
    try:
        if dry_run:
            refs = discover_frames(cfg)
            typer.echo(cfg.to_yaml())
            typer.echo(f"# {len(refs)} frames: first {refs[0].key}, last {refs[-1].key}")
            return
        summary = run_pipeline(cfg, progress=progress)
    except ConfigError as error:
        _fail(str(error))
    typer.echo(summary.table())
    typer.echo(f"summary: {Path(cfg.output.dir) / 'summary.json'}")
    raise typer.Exit(summary.exit_code)


@app.command()
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for the synthetic drive and the outputs.")] = Path("kitti-pu-demo"),
    frames: Annotated[int, typer.Option(help="Frames in the synthetic drive.")] = 3,
    seed: Annotated[int, typer.Option(help="Seed of the synthetic street.")] = 0,
    workers: Annotated[Optional[int], typer.Option(help="LocalCluster worker processes.")] = None,
    progress: Annotated[bool, typer.Option(help="Show a progress bar.")] = True,
    config: ConfigFiles = None,
    set_: SetOptions = None,
) -> None:
    """Make a synthetic KITTI raw drive and densify it end to end (the embedded default)."""
    from .demo import run_demo

    cfg = _build_config(config, {"dask.n_workers": workers}, set_)
    try:
        summary, previews = run_demo(out, cfg, n_frames=frames, seed=seed, progress=progress)
    except ConfigError as error:
        _fail(str(error))
    typer.echo(summary.table())
    for png in previews:
        typer.echo(f"preview: {png}")
    typer.echo(f"outputs: {Path(summary.output_dir)}")
    raise typer.Exit(summary.exit_code)


@app.command()
def info(out: Annotated[Path, typer.Argument(help="An output folder of kitti-pu run.")]) -> None:
    """Summarise an output folder: frames and points per sequence, the last run's result."""
    from .outputs import describe_output

    try:
        typer.echo(describe_output(out))
    except ConfigError as error:
        _fail(str(error))


@app.command()
def preview(
    parquet: Annotated[Path, typer.Argument(help="One output frame (.parquet).")],
    png: Annotated[Optional[Path], typer.Option("--png", help="PNG to write (default: beside the Parquet).")] = None,
) -> None:
    """Render bird's-eye and perspective PNGs of a frame before and after densification."""
    from .preview import preview_parquet

    if not parquet.is_file():
        _fail(f"preview: {parquet} not found")
    target = png or parquet.with_suffix(".png")
    typer.echo(str(preview_parquet(parquet, target)))


@app.command("eval-kitti")
def eval_kitti(
    path: Annotated[Path, typer.Argument(help="KITTI drive, odometry sequence or .bin folder of full 64-beam scans.")],
    out: Annotated[Path, typer.Option("--out", "-o", help="Folder for eval_kitti.csv and eval_kitti.png.")] = Path("kitti-pu-eval"),
    weights: Annotated[Optional[Path], typer.Option(help="CAD-PU weights (default: upsample.weights, cadpu_r4_lidar).")] = None,
    uniform_weights: Annotated[Optional[Path], typer.Option(help="alpha = 1.0 weights (default: the one trained like --weights).")] = None,
    frames: Annotated[Optional[int], typer.Option(help="Evaluate only the first N scans.")] = None,
    config: ConfigFiles = None,
    set_: SetOptions = None,
) -> None:
    """Keep every 4th ring of each scan, densify it 4x with each method, score against the full scan."""
    from cadpu.weights import WeightsError
    from stages.errors import StageError

    from .evaluation.kitti import evaluate_kitti

    cfg = _build_config(config, {}, set_)
    try:
        result = evaluate_kitti(path, out, weights, uniform_weights, frames, cfg, log=typer.echo)
    except (StageError, WeightsError) as error:
        _fail(f"eval-kitti: {error}")
    typer.echo(result.table)
    typer.echo(f"csv: {result.csv_path}")
    typer.echo(f"png: {result.png_path}")


@app.command("config")
def show_config(
    config: ConfigFiles = None,
    set_: SetOptions = None,
) -> None:
    """Validate configuration files and print the resolved configuration."""
    typer.echo(_build_config(config, {}, set_).to_yaml())


def main() -> None:  # pragma: no cover - entry point of `python -m pipeline` (pipeline/__main__.py)
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
