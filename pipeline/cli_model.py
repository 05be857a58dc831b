"""`kitti-pu eval-kitti` and `kitti-pu finetune`: the verbs over the model (see `pipeline.cli`)."""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Optional

import typer

from .cli_common import (DEFAULTS, FLAG, ConfigFiles, FirstOption, LastOption, SequenceOption,
                         SetOptions, WeightsOption, build_config, Command, command_error, shown_default, fail, app)
from .summary import EXIT_FRAMES_FAILED, EXIT_INTERRUPTED


#: finetune's --progress: its bars, not run's per-frame lines.
TrainingProgress = Annotated[
    bool,
    typer.Option("--progress/--no-progress", metavar=FLAG,
                 help="Progress bars while pairs are cut and while training; --no-progress leaves them out, for "
                      "logs (the line per scan and the result are printed either way)."),
]


@app.command("eval-kitti", cls=Command)
def eval_kitti(
    path: Annotated[Path, typer.Argument(metavar="PATH", help="KITTI drive, odometry sequence or .bin folder of full 64-beam scans.")],
    out: Annotated[Path, typer.Option("--out", "-o", metavar="DIR", help=(
        "Folder for eval_kitti.csv (every scan and method), eval_kitti.json (inputs, settings, weights "
        "and checksums) and eval_kitti.png."))] = Path("kitti-pu-eval"),
    weights: WeightsOption = None,
    twin_weights: Annotated[Optional[Path], typer.Option("--twin-weights", metavar="FILE|NAME", show_default="the twin of --weights", help=(
        "Weights compared with --weights (the row 'CAD-PU twin'). By default: for a shipped file, the shipped file "
        "trained on the same data with the other alpha; for a file of your own, the file it was trained or "
        "fine-tuned from, else the pipeline's default."))] = None,
    # the option's former name, still taken; out of the help, where both names cut the column short
    uniform_weights: Annotated[Optional[Path], typer.Option("--uniform-weights", hidden=True)] = None,
    frames: Annotated[Optional[int], typer.Option(metavar="N", show_default="all", help=(
        "Evaluate only the first N scans."))] = None,
    sequence: SequenceOption = None,
    first: FirstOption = None,
    last: LastOption = None,
    config: ConfigFiles = None,
    set_: SetOptions = None,
) -> None:
    """Keep every 4th ring of each scan, densify it 4x with each method, score against the full scan."""
    from cadpu.weights import WeightsError
    from stages.errors import StageError

    from .evaluation.kitti import evaluate_kitti

    if twin_weights is not None and uniform_weights is not None and twin_weights != uniform_weights:
        raise typer.BadParameter("give --twin-weights once (--uniform-weights is its former name)")
    twin_weights = twin_weights if twin_weights is not None else uniform_weights
    cfg = build_config(config, {"input.sequences": sequence, "input.first_frame": first, "input.last_frame": last}, set_)
    try:
        result = evaluate_kitti(path, out, weights, twin_weights, frames, cfg, log=typer.echo)
    except (StageError, WeightsError) as error:
        fail(command_error("eval-kitti", error))
    typer.echo(result.table)
    typer.echo(f"csv: {result.csv_path}")
    typer.echo(f"png: {result.png_path}")
    typer.echo(f"record: {result.record_path}")
    if result.failed:
        count = len(result.failed)
        fail(f"eval-kitti: {count} scan{'' if count == 1 else 's'} not evaluated (left out of the table):\n  "
             + "\n  ".join(result.failed), EXIT_FRAMES_FAILED)


@app.command("finetune", cls=Command)
def finetune_command(
    path: Annotated[Path, typer.Argument(metavar="PATH", help=(
        "KITTI raw drive, odometry sequence, folder of .bin scans or one .bin: full 64-ring scans in KITTI order."))],
    out: Annotated[Path, typer.Option("--out", "-o", metavar="FILE", help=(
        "Weights file to write (and FILE.sha256); the run's logs and checkpoint go to FILE.run/."))],
    weights: WeightsOption = None,
    sequence: SequenceOption = None,
    first: FirstOption = None,
    last: LastOption = None,
    steps: Annotated[Optional[int], typer.Option(metavar="N", show_default=shown_default(DEFAULTS.finetune.steps), help=(
        "Training steps."))] = None,
    resume: Annotated[bool, typer.Option("--resume", metavar=FLAG, show_default=False, help=(
        "Continue the run in FILE.run/ (same scans and settings)."))] = False,
    max_seconds: Annotated[Optional[float], typer.Option(metavar="S", min=0, show_default="no limit", help=(
        "Stop after a checkpoint once this long has passed; --resume continues."))] = None,
    progress: TrainingProgress = True,
    config: ConfigFiles = None,
    set_: SetOptions = None,
) -> None:
    """Fine-tune CAD-PU weights on your own full scans, self-supervised: every 4th ring in, the whole
    scan as truth; the weights of the best score on held-out scans are written."""
    from cadpu.stopping import TrainingStopped
    from cadpu.weights import WeightsError
    from stages.errors import StageError

    from .finetune import InterruptedBeforeTraining, finetune

    options = {"input.path": path, "input.sequences": sequence, "input.first_frame": first,
               "input.last_frame": last, "finetune.steps": steps}
    cfg = build_config(config, options, set_)
    try:
        result = finetune(cfg, out, weights, resume=resume, progress=progress, max_seconds=max_seconds, log=typer.echo)
    except (StageError, WeightsError, ValueError, FileExistsError, FileNotFoundError) as error:
        fail(command_error("finetune", error))
    except TrainingStopped as stopped:  # Ctrl-C or SIGTERM, after a checkpoint and the weights
        fail(f"finetune: {stopped}", stopped.exit_status)
    except InterruptedBeforeTraining:  # it ended in silence (a trial)
        fail("finetune: interrupted before training began (while the scans were read and cut); nothing was "
             "trained and no weights were written", EXIT_INTERRUPTED["SIGINT"])
    except KeyboardInterrupt:  # outside the steps, which stop at a signal themselves (a second Ctrl-C, the last save)
        fail("finetune: interrupted; the run's last checkpoint, if it has one, stands: --resume continues from it",
             EXIT_INTERRUPTED["SIGINT"])
    unchanged = ("; no step scored better than the starting weights, so the file holds them unchanged"
                 if result.heldout_scans and result.best_step == 0 else "")  # said in so many words (a trial)
    scored = (f"held-out non-ground Chamfer {result.heldout_before:.4f} m before, {result.heldout_after:.4f} m "
              f"with the weights of step {result.best_step}{unchanged}" if result.heldout_scans else
              f"no scan held out (one scan, or finetune.validation_share 0): the weights of the last step, "
              f"{result.best_step}, unscored; give two scans or more to choose them by a held-out score")
    # a run stopped by --max-seconds read as a finished one (a trial)
    stopped = (f" of {cfg.finetune.steps} (stopped by --max-seconds; --resume continues)"
               if result.steps < cfg.finetune.steps else "")
    typer.echo(f"{result.train_pairs} training pairs, {result.heldout_scans} scan{'' if result.heldout_scans == 1 else 's'} "
               f"held out; {result.steps} step{'' if result.steps == 1 else 's'}{stopped}; {scored}")
    typer.echo(f"weights: {result.weights} (sha256 {result.checksum[:12]}); use them with "
               f"kitti-pu run PATH --weights {result.weights}")
