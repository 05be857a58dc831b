"""`kitti-pu`: the command line, a thin layer over `pipeline` and `cadpu`.

The verbs over scans and output folders (run, demo, info, preview, config) are here; those over the
model (eval-kitti, finetune) in `cli_model`; what they share in `cli_common`.
Exit codes: 0 all frames done, 2 bad configuration or input, 3 some frames failed, 1 a crash.
"""

from __future__ import annotations

import contextlib
import json
import signal
import sys
from collections import Counter
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Optional

import typer

from .cli_common import (DEFAULTS, FLAG, ConfigFiles, FirstOption, LastOption, Progress, SequenceOption,
                         SetOptions, WeightsOption, build_config, Command, shown_default, fail, app, echo_frame_line)
from .config import ConfigError, PipelineConfig
from .summary import EXIT_FRAMES_FAILED, EXIT_INTERRUPTED, EXIT_OUTPUT_BUSY, SummaryWriteError, Terminated


@app.command(cls=Command)
def run(
    # as text, not Path: Path("") is ".", and an empty argument (a script's unset variable) read
    # the working folder; the configuration refuses it
    path: Annotated[Optional[str], typer.Argument(metavar="PATH", show_default=False, help=(
        "KITTI raw base, date or drive folder; odometry base or sequence folder; a folder of .bin "
        "scans; or one .bin file."))] = None,
    out: Annotated[Optional[str], typer.Option("--out", "-o", metavar="DIR", show_default=shown_default(DEFAULTS.output.dir),
                                               help="Output folder.")] = None,
    format_: Annotated[Optional[str], typer.Option(
        "--format", "-f", metavar="FORMATS", show_default=shown_default(DEFAULTS.output.formats), help=(
            "Output formats, comma-separated: parquet, ply, kitti (a KITTI .bin mirror of the input "
            "layout under OUT/kitti)."))] = None,
    kind: Annotated[Optional[str], typer.Option(metavar="KIND", show_default=shown_default(DEFAULTS.input.kind), help=(
        "Input layout: auto, raw, odometry or bin."))] = None,
    sequence: SequenceOption = None,
    first: FirstOption = None,
    last: LastOption = None,
    step: Annotated[Optional[int], typer.Option(metavar="N", show_default=shown_default(DEFAULTS.input.step), help=(
        "Take every N-th frame number from --first (first, first + N, ...; by the numbers in the scans' names, "
        "not by their count)."))] = None,
    ratio: Annotated[Optional[int], typer.Option("--ratio", "-r", metavar="N", show_default=shown_default(DEFAULTS.upsample.ratio), help=(
        "Upsampling ratio (4 is the trained one)."))] = None,
    weights: WeightsOption = None,
    ground: Annotated[Optional[str], typer.Option(metavar="METHOD", show_default=shown_default(DEFAULTS.ground.method), help=(
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
    """Densify every frame under PATH and write Parquet/PLY (and a KITTI copy with -f kitti) plus a
    run summary."""
    options = {
        "input.path": path, "input.kind": kind, "input.sequences": sequence, "input.first_frame": first,
        "input.last_frame": last, "input.step": step, "output.dir": out, "upsample.ratio": ratio,
        "upsample.weights": weights, "ground.method": ground, "dask.scheduler": scheduler,
        "dask.n_workers": workers, "output.overwrite": overwrite or None, "output.formats": format_,
    }
    # From here a signal ends the run with one line and its exit status, also while the runner's
    # modules (Dask, torch) load: SIGTERM then ended the program without a word, SIGINT in a traceback.
    try:
        with _sigterm_as_exception():
            cfg = build_config(config, options, set_)
            from .preflight import missing_metadata, preflight
            from .runner import OutputBusy, RunInterrupted, earlier_hashes, output_busy, plan_frames, run_pipeline

            try:
                if dry_run:
                    given = cfg
                    cfg, refs, checksum = preflight(cfg)
                    typer.echo(cfg.to_yaml())
                    typer.echo(config_hash_line(cfg))
                    plan = plan_frames(cfg, refs, checksum, earlier_hashes(given, cfg))
                    # of the frames a run would load, or refuses for a file missing: finished ones,
                    # skipped, were said to fail
                    for line in missing_metadata(plan.todo + [ref for ref, _ in plan.refused]):
                        typer.echo(f"# warning: {line}")
                    per_sequence = Counter(f"{ref.dataset}/{ref.sequence}" for ref in refs)
                    typer.echo(f"# {len(refs)} frame{'s' if len(refs) != 1 else ''}: first {refs[0].key}, last "
                               f"{refs[-1].key}; " + ", ".join(f"{name}: {n}" for name, n in per_sequence.items()))
                    typer.echo(f"# a run now: {plan.describe()}")
                    # reached and checked when a run would reach it: for its frames, or first when
                    # it adds formats (one whose stored file is damaged needs the network after all)
                    if cfg.dask.scheduler and (plan.todo or plan.exports):
                        from .cluster import describe_existing_cluster

                        typer.echo(f"# cluster: {describe_existing_cluster(cfg.dask.scheduler)}")
                    if output_busy(Path(cfg.output.dir)):
                        typer.echo(f"# warning: another kitti-pu run is writing to {cfg.output.dir}: a run now would "
                                   f"do nothing and exit {EXIT_OUTPUT_BUSY}")
                    return
                on_report = None if progress else echo_frame_line
                # the signals are held from the run's last steps until its result is printed, on every
                # path: the run is over, and its summary and exit status stand
                with contextlib.ExitStack() as signals_held:
                    try:
                        summary = run_pipeline(cfg, progress=progress, on_report=on_report,
                                               signals_held=signals_held)
                    except RunInterrupted as stop:
                        typer.echo(stop.summary.table())
                        typer.echo(f"kitti-pu: {stop}; summary: {Path(stop.summary.output_dir) / 'summary.json'}",
                                   err=True)
                        raise typer.Exit(stop.summary.exit_code) from None
                    except SummaryWriteError as error:  # the frames are written; only the run's summary is not
                        typer.echo(error.summary.table())
                        # a stop keeps its own status; otherwise 3, as the summary is missing
                        status = error.summary.exit_code if error.summary.interrupted else EXIT_FRAMES_FAILED
                        fail(f"{error}: the frames above are as the table says; exit {status} as the "
                             "run's summary is missing", status)
                    typer.echo(summary.table())
                    typer.echo(f"summary: {Path(cfg.output.dir) / 'summary.json'}")
                    if summary.record_missing:
                        typer.echo(f"kitti-pu: {summary.record_missing}: exit {EXIT_FRAMES_FAILED} as the run's "
                                   "record is missing (summary.json says so)", err=True)
            except OutputBusy as error:
                fail(str(error), EXIT_OUTPUT_BUSY)
    except ConfigError as error:
        fail(str(error))
    except (KeyboardInterrupt, Terminated) as stop:  # before the run began its frames: nothing was done
        name = "SIGTERM" if isinstance(stop, Terminated) else "SIGINT"
        fail(f"stopped by {name} before the run began; no frame was processed", EXIT_INTERRUPTED[name])
    raise typer.Exit(summary.exit_code)


@contextlib.contextmanager
def _sigterm_as_exception() -> Iterator[None]:
    """While inside, SIGTERM raises `summary.Terminated` in the main thread (as SIGINT raises
    KeyboardInterrupt), so that the run writes its summary before the process ends."""
    def terminate(signum: int, frame: object) -> None:
        raise Terminated()

    previous = signal.signal(signal.SIGTERM, terminate)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


@app.command(cls=Command)
def demo(
    out: Annotated[Path, typer.Option("--out", "-o", metavar="DIR",
                                      help="Folder for the synthetic drive and the outputs.")] = Path("kitti-pu-demo"),
    frames: Annotated[int, typer.Option(metavar="N", min=1, help="Frames in the synthetic drive.")] = 3,
    seed: Annotated[int, typer.Option(metavar="N", help="Seed of the synthetic street.")] = 0,
    workers: Annotated[Optional[int], typer.Option(metavar="N", show_default="one per core, at most 4", help=(
        "LocalCluster worker processes."))] = None,
    progress: Progress = True,
    config: ConfigFiles = None,
    set_: SetOptions = None,
) -> None:
    """Make a synthetic KITTI raw drive and densify it end to end (the embedded default)."""
    from .demo import run_demo
    from .preflight import check_output_target

    try:  # a file in the way gave a traceback from deep in the simulator
        check_output_target(out, "demo: --out")
    except ConfigError as error:
        fail(str(error))
    cfg = build_config(config, {"dask.n_workers": workers}, set_)
    try:
        summary, previews = run_demo(out, cfg, n_frames=frames, seed=seed, progress=progress,
                                     on_report=None if progress else echo_frame_line)
    except ConfigError as error:
        fail(str(error))
    except SummaryWriteError as error:
        fail(str(error), EXIT_FRAMES_FAILED)
    typer.echo(summary.table())
    for png in previews:
        typer.echo(f"preview: {png}")
    typer.echo(f"outputs: {Path(summary.output_dir)}")
    raise typer.Exit(summary.exit_code)


@app.command(cls=Command)
def info(
    out: Annotated[Path, typer.Argument(metavar="OUT", help="An output folder of kitti-pu run.")],
    as_json: Annotated[bool, typer.Option("--json", metavar=FLAG, show_default=False,
                                          help="Print JSON instead of text.")] = False,
    verify: Annotated[bool, typer.Option("--verify", metavar=FLAG, show_default=False,
                                         help="Also read every frame file whole, in every format, and every scan; exit 3 "
                                              "when a file is damaged, a scan holds other bytes than its frame was "
                                              "made from, or the KITTI mirror's labels are not the input's.")] = False,
) -> None:
    """Summarise an output folder: frames and points, the last run's stage timings, the model and
    the configurations that made each sequence."""
    from .info import damaged_frame_files, folder_info, format_info, rewritten_sources, stale_mirror_labels

    try:
        found = folder_info(out)
    except ConfigError as error:
        fail(str(error))
    if verify:
        found["damaged"] = damaged_frame_files(out)
        found["sources_rewritten"] = rewritten_sources(out)
        found["labels_stale"] = stale_mirror_labels(out)
    typer.echo(json.dumps(found, indent=2) if as_json else format_info(found))
    if verify and found["damaged"]:
        typer.echo(f"{len(found['damaged'])} damaged frame file(s): remove them and run again to redo those frames",
                   err=True)
    if verify and found["sources_rewritten"]:
        typer.echo(f"{len(found['sources_rewritten'])} scan(s) rewritten since their frames were made: touch them and "
                   "run again to redo those frames", err=True)
    if verify and found["labels_stale"]:
        typer.echo(f"{len(found['labels_stale'])} mirrored frame(s) with stale SemanticKITTI labels: run again "
                   "selecting those frames", err=True)
    if verify and (found["damaged"] or found["sources_rewritten"] or found["labels_stale"]):
        raise typer.Exit(EXIT_FRAMES_FAILED)


@app.command(cls=Command)
def preview(
    frame: Annotated[Path, typer.Argument(metavar="FRAME", help="One output frame: its .parquet, .ply or KITTI .bin file.")],
    png: Annotated[Optional[Path], typer.Option("--png", metavar="FILE",
                                                show_default="OUT/preview/DATASET/SEQUENCE/N.png for a frame of OUT, else NAME.png here, NAME the file's",
                                                help="PNG to write.")] = None,
) -> None:
    """Render one PNG of a frame before and after densification: the whole frame, then side views of
    a car, a wall edge and a pole found in it."""
    from stages.write_kitti import sidecar_path

    from .preview import FRAME_FORMATS, UnreadableFrame, data_folder, default_png_path, preview_frame

    if frame.is_dir():
        fail(f"preview: {frame} is a folder; give one frame's file ({', '.join(FRAME_FORMATS)})")
    if not frame.is_file():
        fail(f"preview: {frame} not found")
    if frame.suffix.lower() not in FRAME_FORMATS:
        fail(f"preview: {frame} is not a kitti-pu output frame (one of {', '.join(FRAME_FORMATS)})")
    if FRAME_FORMATS[frame.suffix.lower()] == "kitti" and not sidecar_path(frame).is_file():
        fail(f"preview: {frame} is not a kitti-pu output frame (a .bin of the KITTI mirror has its sidecar, "
             f"{sidecar_path(frame).name} in kitti_pu/ beside it); run `kitti-pu run` on the scans first")
    target = png or default_png_path(frame)
    if target.suffix.lower() != ".png":  # also keeps a PNG from replacing a frame or summary.json
        fail(f"preview: --png {target}: the preview is a PNG image; give a file name ending in .png")
    inside = data_folder(target)
    if inside is not None:
        fail(f"preview: {target} is inside the data folder {inside} of a kitti-pu output, where readers would "
             "take it for data; choose another --png")
    try:
        written = preview_frame(frame, target)
    except UnreadableFrame as error:
        fail(f"preview: {frame} is not a readable kitti-pu output frame ({error})")
    except OSError as error:
        fail(f"preview: cannot write {target} ({error.strerror or error})")
    typer.echo(str(written))


@app.command("config", cls=Command)
def show_config(
    config: ConfigFiles = None,
    set_: SetOptions = None,
) -> None:
    """Validate configuration files (and that the weights load and make the ratio) and print the
    resolved configuration."""
    from .preflight import check_environment, check_weights, with_engine_that_runs

    cfg = build_config(config, {}, set_)
    try:
        check_environment(cfg)
        check_weights(cfg)
    except ConfigError as error:
        fail(str(error))
    typer.echo(cfg.to_yaml())
    typer.echo(config_hash_line(with_engine_that_runs(cfg)))  # what a run records: the engine it falls back to


def config_hash_line(cfg: PipelineConfig) -> str:
    """The YAML comment naming the hash that the frames made with `cfg` record (`kitti-pu info`
    lists frames by it)."""
    return f"# config hash: {cfg.output_hash()} (recorded by every frame made with these settings; kitti-pu info)"


from . import cli_model  # noqa: E402,F401  (registers eval-kitti and finetune after the verbs above)


def main() -> None:  # pragma: no cover - entry point of `python -m pipeline` (pipeline/__main__.py)
    app()


if __name__ == "__main__":  # pragma: no cover
    sys.exit(main())
