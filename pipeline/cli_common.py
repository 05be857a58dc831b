"""What every `kitti-pu` verb shares: the typer app, its option types and error handling.

Exit codes: 0 all frames done, 2 bad configuration or input, 3 some frames failed, 1 a crash.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Any, Optional

import typer
from typer.core import TyperCommand, TyperGroup
import yaml

from cadpu import yaml_text

from .config import ConfigError, PipelineConfig, load_config
from .process_end import end_process
from .summary import EXIT_BAD_CONFIG, FrameReport


def _no_value_shown(option: Any) -> Any:
    if option is not None:
        option.metavar = ""
    return option


def _reflowed(text: str | None) -> str | None:
    """`text` with the line breaks inside each paragraph made spaces: the help shows a docstring's
    lines as they are, so the command list broke mid-sentence where the source wrapped."""
    if text is None:
        return None
    paragraphs = text.strip().split("\n\n")
    return "\n\n".join(" ".join(line.strip() for line in paragraph.splitlines()) for paragraph in paragraphs)


class Command(TyperCommand):
    """A command whose -h/--help shows no value type (typer shows "<bool>", as if it took one), and
    whose help text flows as one line a paragraph (`_reflowed`)."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        super().__init__(*args, **kwargs)
        self.help = _reflowed(self.help)

    def get_help_option(self, ctx: Any) -> Any:
        return _no_value_shown(super().get_help_option(ctx))


class Group(TyperGroup):
    """The top-level group, with the help option of `Command`."""

    def get_help_option(self, ctx: Any) -> Any:
        return _no_value_shown(super().get_help_option(ctx))


class App(typer.Typer):
    """The `kitti-pu` program. Run as a program (standalone, as the console script and
    `python -m pipeline` run it), it ends with `end_process` instead of the interpreter's
    teardown, which torch makes last a noticeable part of a second; called with
    `standalone_mode=False` (or through click's test runner) it returns or raises as any typer
    app."""

    def __call__(self, *args: Any, **kwargs: Any) -> Any:
        if kwargs.get("standalone_mode", True) is False:
            return super().__call__(*args, **kwargs)
        try:
            super().__call__(*args, **kwargs)
            code: Any = 0
        except SystemExit as stop:
            code = stop.code
        end_process(code)


app = App(
    cls=Group,
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
    typer.Option("--config", "-c", metavar="FILE",
                 help="YAML override file, or a preset's name (unordered_scans), applied in order (repeatable)."),
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
        from .chain import tool_version

        typer.echo(f"kitti-pu {tool_version()}")
        raise typer.Exit()


@app.callback()
def main_options(
    version: Annotated[bool, typer.Option("--version", metavar=FLAG, callback=_version, is_eager=True,
                                          help="Print the version and exit.")] = False,
) -> None:
    """Densify KITTI LiDAR scans with CAD-PU, on Dask."""


def shown_default(value: object) -> str:
    """An option's default as its help shows it (`show_default`): the configuration's default."""
    if isinstance(value, (list, tuple)):
        return ",".join(map(str, value))
    return str(value)


#: --weights, in every verb that loads the network.
WeightsOption = Annotated[Optional[Path], typer.Option(metavar="FILE|NAME", show_default=shown_default(DEFAULTS.upsample.weights),
                                                       help="CAD-PU weight file, or the name of a shipped one.")]


#: Which scans a verb takes: --sequence, --first, --last (the input section's selection).
SequenceOption = Annotated[Optional[list[str]], typer.Option("--sequence", "-s", metavar="NAME", show_default="all", help=(
    "Drive or sequence to take (repeatable; 0 and 00 are the same)."))]
FirstOption = Annotated[Optional[int], typer.Option(metavar="N", show_default=shown_default(DEFAULTS.input.first_frame), help=(
    "First frame index."))]
LastOption = Annotated[Optional[int], typer.Option(metavar="N", show_default="the last", help=(
    "Last frame index (inclusive)."))]


#: The outcomes `--no-progress` gives a line as each frame ends: the frames whose work ended. A
#: skipped frame (a scheduled rerun of a large set skips most) and one a stop or a lost cluster
#: left undone are counted in the table's last line only (lines for some of them, and none after
#: a Ctrl-C, read as if only those were interrupted: an operator's trial).
FRAME_LINE_STATUSES = ("done", "replaced", "failed")


def echo_frame_line(report: FrameReport) -> None:
    """Print `frame_line(report)` when the frame's outcome gets one (`FRAME_LINE_STATUSES`)."""
    if report.status in FRAME_LINE_STATUSES:
        typer.echo(frame_line(report))


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
            raise ConfigError(f"--set {item!r}: expected KEY=VALUE, e.g. --set upsample.ratio=16")
        try:
            overrides[key.strip()] = yaml_text.read_yaml(value)  # as the config files are read
        except yaml.YAMLError as error:  # a traceback, exit 1, before
            raise ConfigError(f"--set {item!r}: the value is not valid YAML {yaml_text.describe_error(error)}") from None
    return overrides


def fail(message: str, code: int = EXIT_BAD_CONFIG) -> None:
    typer.echo(f"kitti-pu: {message}", err=True)
    raise typer.Exit(code)


def command_error(command: str, error: BaseException) -> str:
    """The line for an error that ended `command`: prefixed with the command's name unless the
    error names its stage ("[finetune] scan.bin: ...", a `StageError`) or the message starts with
    the command's name."""
    from stages.errors import StageError

    message = str(error)
    named = isinstance(error, StageError) or message.startswith(f"{command}:")
    return message if named else f"{command}: {message}"


def build_config(files: list[Path] | None, options: dict[str, Any], sets: list[str] | None) -> PipelineConfig:
    try:
        return load_config(files or [], options, _parse_sets(sets))
    except ConfigError as error:
        fail(str(error))
        raise  # unreachable: fail exits
