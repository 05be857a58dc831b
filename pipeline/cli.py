"""`kitti-pu`: the command line, a thin layer over `pipeline` and `cadpu`.

Exit codes: 0 all frames done, 2 bad configuration or input, 3 some frames failed, 1 a crash.
"""

from __future__ import annotations

import contextlib
import json
import signal
import sys
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any, Optional

import typer
from typer.core import TyperCommand, TyperGroup
import yaml

from .config import ConfigError, PipelineConfig, load_config
from .summary import EXIT_BAD_CONFIG, EXIT_FRAMES_FAILED, EXIT_OUTPUT_BUSY, FrameReport, SummaryWriteError


def _no_value_shown(option: Any) -> Any:
    if option is not None:
        option.metavar = ""
    return option


class _Command(TyperCommand):
    """A command whose -h/--help shows no value type (typer shows "<bool>", as if it took one)."""

    def get_help_option(self, ctx: Any) -> Any:
        return _no_value_shown(super().get_help_option(ctx))


class _Group(TyperGroup):
    """The top-level group, with the help option of `_Command`."""

    def get_help_option(self, ctx: Any) -> Any:
        return _no_value_shown(super().get_help_option(ctx))


app = typer.Typer(
    cls=_Group,
    add_completion=False,
    no_args_is_help=True,
    help="Densify KITTI LiDAR scans with CAD-PU, on Dask.",
    pretty_exceptions_enable=False,
    context_settings={"help_option_names": ["-h", "--help"]},
)

#: The settings' defaults, shown in the help of options whose value otherwise comes from the config.
DEFAULTS = PipelineConfig()
#: A flag (no value): typer would otherwise show "<bool>" as if it took one.
FLAG = ""

ConfigFiles = Annotated[
    Optional[list[Path]],
    typer.Option("--config", "-c", metavar="FILE", help="YAML override file, applied in order (repeatable)."),
]
SetOptions = Annotated[
    Optional[list[str]],
    typer.Option("--set", metavar="KEY=VALUE",
                 help="Override any key: --set tile.overlap=2.0 (value read as YAML; repeatable)."),
]
Progress = Annotated[
    bool,
    typer.Option("--progress/--no-progress", metavar=FLAG,
                 help="A progress bar; --no-progress prints one line per finished frame instead "
                      "(key, status, points, seconds), for logs."),
]


def _version(value: bool) -> None:
    if value:
        from .runner import tool_version

        typer.echo(f"kitti-pu {tool_version()}")
        raise typer.Exit()


@app.callback()
def main_options(
    version: Annotated[bool, typer.Option("--version", metavar=FLAG, callback=_version, is_eager=True,
                                          help="Print the version and exit.")] = False,
) -> None:
    """Densify KITTI LiDAR scans with CAD-PU, on Dask."""


def _default(value: object) -> str:
    """An option's default as its help shows it (`show_default`): the configuration's default."""
    if isinstance(value, (list, tuple)):
        return ",".join(map(str, value))
    return str(value)


#: --weights, in every verb that loads the network.
WeightsOption = Annotated[Optional[Path], typer.Option(metavar="FILE|NAME", show_default=_default(DEFAULTS.upsample.weights),
                                                       help="CAD-PU weight file, or the name of a shipped one.")]


def frame_line(report: FrameReport) -> str:
    """The line `--no-progress` prints when a frame finishes: key, status, points in -> out,
    seconds (the sum of its stage timings), and the error of a failed frame."""
    seconds = sum(report.timings.values())
    line = f"{report.key} {report.status} {report.points_in} -> {report.points_out} points {seconds:.2f} s"
    return f"{line}: {report.error}" if report.error else line


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


@app.command(cls=_Command)
def run(
    path: Annotated[Optional[Path], typer.Argument(metavar="PATH", show_default=False, help=(
        "KITTI raw base, date or drive folder; odometry base or sequence folder; a folder of .bin "
        "scans; or one .bin file."))] = None,
    out: Annotated[Optional[Path], typer.Option("--out", "-o", metavar="DIR", show_default=_default(DEFAULTS.output.dir),
                                                help="Output folder.")] = None,
    format_: Annotated[Optional[str], typer.Option(
        "--format", "-f", metavar="FORMATS", show_default=_default(DEFAULTS.output.formats), help=(
            "Output formats, comma-separated: parquet, ply, kitti (a KITTI .bin mirror of the input "
            "layout under OUT/kitti)."))] = None,
    kind: Annotated[Optional[str], typer.Option(metavar="KIND", show_default=_default(DEFAULTS.input.kind), help=(
        "Input layout: auto, raw, odometry or bin."))] = None,
    sequence: Annotated[Optional[list[str]], typer.Option("--sequence", "-s", metavar="NAME", show_default="all", help=(
        "Drive or sequence to take (repeatable; 0 and 00 are the same)."))] = None,
    first: Annotated[Optional[int], typer.Option(metavar="N", show_default=_default(DEFAULTS.input.first_frame), help=(
        "First frame index."))] = None,
    last: Annotated[Optional[int], typer.Option(metavar="N", show_default="the last", help=(
        "Last frame index (inclusive)."))] = None,
    step: Annotated[Optional[int], typer.Option(metavar="N", show_default=_default(DEFAULTS.input.step), help=(
        "Take every N-th frame."))] = None,
    ratio: Annotated[Optional[int], typer.Option("--ratio", "-r", metavar="N", show_default=_default(DEFAULTS.upsample.ratio), help=(
        "Upsampling ratio (4 is the trained one)."))] = None,
    weights: WeightsOption = None,
    ground: Annotated[Optional[str], typer.Option(metavar="METHOD", show_default=_default(DEFAULTS.ground.method), help=(
        "Ground method: patchwork, ransac, patchworkpp."))] = None,
    scheduler: Annotated[Optional[str], typer.Option(metavar="ADDRESS", show_default="a LocalCluster", help=(
        "Address of an existing Dask scheduler, e.g. tcp://host:8786."))] = None,
    workers: Annotated[Optional[int], typer.Option(metavar="N", show_default="one per core, at most 4", help=(
        "LocalCluster worker processes."))] = None,
    overwrite: Annotated[bool, typer.Option("--overwrite", metavar=FLAG, show_default=False,
                                            help="Redo frames whose outputs exist.")] = False,
    dry_run: Annotated[bool, typer.Option("--dry-run", metavar=FLAG, show_default=False,
                                          help="Print the resolved configuration and frames, then stop.")] = False,
    progress: Progress = True,
    config: ConfigFiles = None,
    set_: SetOptions = None,
) -> None:
    """Densify every frame under PATH and write Parquet/PLY plus a run summary."""
    from .preflight import preflight
    from .runner import OutputBusy, RunInterrupted, run_pipeline

    options = {
        "input.path": path, "input.kind": kind, "input.sequences": sequence, "input.first_frame": first,
        "input.last_frame": last, "input.step": step, "output.dir": out, "upsample.ratio": ratio,
        "upsample.weights": weights, "ground.method": ground, "dask.scheduler": scheduler,
        "dask.n_workers": workers, "output.overwrite": overwrite or None, "output.formats": format_,
    }
    cfg = _build_config(config, options, set_)
    try:
        if dry_run:
            cfg, refs, _ = preflight(cfg)
            typer.echo(cfg.to_yaml())
            typer.echo(f"# {len(refs)} frames: first {refs[0].key}, last {refs[-1].key}")
            return
        on_report = None if progress else (lambda report: typer.echo(frame_line(report)))
        with _sigterm_as_exception():
            summary = run_pipeline(cfg, progress=progress, on_report=on_report)
    except ConfigError as error:
        _fail(str(error))
    except OutputBusy as error:
        _fail(str(error), EXIT_OUTPUT_BUSY)
    except RunInterrupted as stop:
        typer.echo(stop.summary.table())
        typer.echo(f"kitti-pu: {stop}; summary: {Path(stop.summary.output_dir) / 'summary.json'}", err=True)
        raise typer.Exit(stop.signal_exit) from None
    except SummaryWriteError as error:  # the frames are written; only the record of the run is not
        _fail(str(error), EXIT_FRAMES_FAILED)
    typer.echo(summary.table())
    typer.echo(f"summary: {Path(cfg.output.dir) / 'summary.json'}")
    raise typer.Exit(summary.exit_code)


@contextlib.contextmanager
def _sigterm_as_exception() -> Iterator[None]:
    """While inside, SIGTERM raises `runner.Terminated` in the main thread (as SIGINT raises
    KeyboardInterrupt), so that the run writes its summary before the process ends."""
    from .runner import Terminated

    def terminate(signum: int, frame: object) -> None:
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@app.command(cls=_Command)
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", metavar="DIR",
                                      help="Folder for the synthetic drive and the outputs.")] = Path("kitti-pu-demo"),
    frames: Annotated[int, typer.Option(metavar="N", help="Frames in the synthetic drive.")] = 3,
    seed: Annotated[int, typer.Option(metavar="N", help="Seed of the synthetic street.")] = 0,
    workers: Annotated[Optional[int], typer.Option(metavar="N", show_default="one per core, at most 4", help=(
        "LocalCluster worker processes."))] = None,
    progress: Progress = True,
    config: ConfigFiles = None,
    set_: SetOptions = None,
) -> None:
    """Make a synthetic KITTI raw drive and densify it end to end (the embedded default)."""
    from .demo import run_demo

    cfg = _build_config(config, {"dask.n_workers": workers}, set_)
    try:
        summary, previews = run_demo(out, cfg, n_frames=frames, seed=seed, progress=progress,
                                     on_report=None if progress else (lambda report: typer.echo(frame_line(report))))
    except ConfigError as error:
        _fail(str(error))
    except SummaryWriteError as error:
        _fail(str(error), EXIT_FRAMES_FAILED)
    typer.echo(summary.table())
    for png in previews:
        typer.echo(f"preview: {png}")
    typer.echo(f"outputs: {Path(summary.output_dir)}")
    raise typer.Exit(summary.exit_code)


@app.command(cls=_Command)
def info(
    out: Annotated[Path, typer.Argument(metavar="OUT", help="An output folder of kitti-pu run.")],
    as_json: Annotated[bool, typer.Option("--json", metavar=FLAG, show_default=False,
                                          help="Print JSON instead of text.")] = False,
) -> None:
    """Summarise an output folder: frames and points, the last run's stage timings, the model and
    the configurations that made each sequence."""
    from .info import folder_info, format_info

    try:
        found = folder_info(out)
    except ConfigError as error:
        _fail(str(error))
    typer.echo(json.dumps(found, indent=2) if as_json else format_info(found))


@app.command(cls=_Command)
def preview(
    parquet: Annotated[Path, typer.Argument(metavar="PARQUET", help="One output frame (.parquet).")],
    png: Annotated[Optional[Path], typer.Option("--png", metavar="FILE",
                                                show_default="OUT/preview/DATASET/SEQUENCE/N.png for a frame of OUT, else N.png here",
                                                help="PNG to write.")] = None,
) -> None:
    """Render bird's-eye and perspective PNGs of a frame before and after densification."""
    from .preview import default_png_path, hive_folder, preview_parquet

    if not parquet.is_file():
        _fail(f"preview: {parquet} not found")
    if parquet.suffix != ".parquet":
        _fail(f"preview: {parquet} is not a kitti-pu output frame (.parquet); run `kitti-pu run` on the scans first")
    target = png or default_png_path(parquet)
    hive = hive_folder(target)
    if hive is not None:
        _fail(f"preview: {target} is inside the Hive folder {hive}, where readers would take it for "
              "data; choose another --png")
    typer.echo(str(preview_parquet(parquet, target)))


@app.command("eval-kitti", cls=_Command)
def eval_kitti(
    path: Annotated[Path, typer.Argument(metavar="PATH", help="KITTI drive, odometry sequence or .bin folder of full 64-beam scans.")],
    out: Annotated[Path, typer.Option("--out", "-o", metavar="DIR", help="Folder for eval_kitti.csv and eval_kitti.png.")] = Path("kitti-pu-eval"),
    weights: WeightsOption = None,
    uniform_weights: Annotated[Optional[Path], typer.Option(metavar="FILE|NAME", show_default="the one trained like --weights", help=(
        "alpha = 1.0 weights."))] = None,
    frames: Annotated[Optional[int], typer.Option(metavar="N", show_default="all", help=(
        "Evaluate only the first N scans."))] = None,
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


@app.command("config", cls=_Command)
def show_config(
    config: ConfigFiles = None,
    set_: SetOptions = None,
) -> None:
    """Validate configuration files (and that the weights load and make the ratio) and print the
    resolved configuration."""
    from .preflight import check_environment, check_weights

    cfg = _build_config(config, {}, set_)
    try:
        check_environment(cfg)
        check_weights(cfg)
    except ConfigError as error:
        _fail(str(error))
    typer.echo(cfg.to_yaml())


def main() -> None:  # pragma: no cover - entry point of `python -m pipeline` (pipeline/__main__.py)
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
