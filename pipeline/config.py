"""The pipeline's typed configuration: defaults here, overridden by YAML files and CLI options.

One `PipelineConfig` holds every setting. `load_config` merges, in order, the defaults, any number
of YAML files and a dict of dotted-key overrides (``{"upsample.ratio": 16}``), then validates the
result. Unknown keys and bad values raise `ConfigError` with a message naming the key.
"""

from __future__ import annotations

import difflib
import hashlib
import json
from pathlib import Path
from typing import Any, Literal

import pydantic
import yaml
from pydantic import ConfigDict, Field, field_validator

from cadpu import yaml_text
from stages.fill import Options as FillOptions
from stages.ground import Options as GroundOptions
from stages.load import Options as LoadOptions
from stages.options import StrictSwitches
from stages.snap import Options as SnapOptions
from stages.stitch import Options as StitchOptions
from stages.tile import Options as TileOptions
from stages.upsample import Options as UpsampleOptions
from stages.write import Options as WriteOptions


class ConfigError(ValueError):
    """A configuration file, key or value is invalid; the message names it."""


class _Section(StrictSwitches):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)  # as StageOptions


class OutputConfig(WriteOptions):
    """Where and how results are written (`stages.write.Options`), and whether finished frames are
    redone (`overwrite`)."""

    overwrite: bool = False


class DaskConfig(_Section):
    """The cluster: a LocalCluster sized to the machine, or an existing scheduler's address.

    n_workers: worker processes of the LocalCluster (None = one per core, at most 4).
    threads_per_worker: frames each LocalCluster worker runs at once (None = the cores per worker
        when torch_threads is not set, else 1; `pipeline.cluster.plan_cluster`).
    torch_threads: torch intra-op threads per frame (None = the cores per frame, at least 1).
    max_in_flight: frames submitted at once (None = 2 per worker thread); bounds memory.
    memory_limit: per worker of the LocalCluster: "auto", a size ("4GiB"), a number of bytes, or a
        share of the machine's memory (0.5), as Dask reads it.
    dashboard: the LocalCluster's Dask dashboard, on a free loopback port whose link the run prints.
    no_workers_timeout: seconds a run waits while its cluster has no workers (at the start, or
        after losing them all) before it stops; the frames not done are then `interrupted`
        (exit 3) and the output folder's lock is released for the next run.
    With `scheduler`, n_workers, threads_per_worker, memory_limit and dashboard are refused: an
    existing cluster keeps its own.
    """

    scheduler: str | None = None
    n_workers: int | None = Field(None, ge=1)
    threads_per_worker: int | None = Field(None, ge=1)
    torch_threads: int | None = Field(None, ge=1)
    max_in_flight: int | None = Field(None, ge=1)
    memory_limit: str | int | float = "auto"
    dashboard: bool = False
    no_workers_timeout: float = Field(120.0, gt=0)

    @field_validator("memory_limit", mode="before")
    @classmethod
    def _not_a_flag(cls, value: object) -> object:
        if isinstance(value, bool):  # YAML's true would pass as 1, all the machine's memory
            raise ValueError(f"{value!r} is not 'auto', a size such as '4GiB', a number of bytes, nor a share "
                             "of the machine's memory such as 0.5")
        return value


class FinetuneConfig(_Section):
    """Self-supervised fine-tuning on the user's own 64-ring scans (`kitti-pu finetune`,
    `pipeline.finetune`; how the defaults were chosen: docs/results.md, "Fine-tuning").

    steps: generator updates of batch_size pairs. lr: Adam's generator learning rate (constant).
    pairs_per_scan: at most this many training pairs from one scan (spread over the 4 ring
    offsets). max_pairs: at most this many pairs in all (scans are then taken evenly spaced; about
    27 KB a pair in memory). validation_share: share of the scans (at least one when there are two
    or more) held out: the written weights are those of the best held-out score.
    validate_every / checkpoint_every: steps between held-out scores / checkpoints.
    threads: torch threads (0 = torch's default). seed: data draws, batches and expansion draws.
    objective: "emd" (the base file's) or "snapped_chamfer" (the Chamfer distance after ring
    snapping that `eval-kitti` scores: `cadpu.losses.snapped_chamfer`). augmentation: "full" or
    "azimuth" (a rotation about the vertical alone: `cadpu.data.AUGMENTATIONS`).
    """

    steps: int = Field(1500, ge=1)
    batch_size: int = Field(8, ge=1)
    lr: float = Field(3e-4, gt=0.0)
    pairs_per_scan: int = Field(400, ge=1)
    max_pairs: int = Field(16000, ge=1)
    validation_share: float = Field(0.25, ge=0.0, lt=1.0)
    validate_every: int = Field(100, ge=1)
    checkpoint_every: int = Field(100, ge=1)
    threads: int = Field(0, ge=0)
    seed: int = 0
    objective: Literal["emd", "snapped_chamfer"] = "emd"
    augmentation: Literal["full", "azimuth"] = "full"


#: Keys of earlier versions and where they went (named in the error a config that still uses them gets).
RENAMED_KEYS = {"stitch.snap_to_rings": "snap.enabled", "stitch.range_tolerance": "snap.range_tolerance",
                "stitch.fill_ground": "fill.enabled"}

#: Keys of the input section that change a frame's points (what the load stage keeps).
INPUT_POINT_KEYS = ("max_range", "min_range", "max_out_of_range_share")

#: Version of what the stages write for given settings, part of `PipelineConfig.output_hash`: bumped
#: when a change to a stage's code changes the points or labels it writes, so that a resumed run
#: redoes the frames an older version wrote (reported `replaced (config changed)`) instead of
#: mixing both in one folder. 2: the ground method's step 5d and snapping in elevation order.
#: 3: returns within `input.min_range` dropped at load; a partial drive's frames timed and posed
#: by their own frame numbers. Not bumped when load began to drop repeated points (2026-11-27):
#: KITTI's scans and the demo's hold none, so their frames are unchanged, and a bump would have
#: every finished frame of every folder redone; a scan that holds repeats keeps its earlier frame
#: until `--overwrite`.
OUTPUT_VERSION = 3
#: The sections whose settings change a frame's output points (`PipelineConfig.output_hash`).
OUTPUT_SECTIONS = ("ground", "tile", "upsample", "stitch", "snap", "fill")
#: Settings added after outputs were written, with the value that gives the output of before. At
#: that value they are left out of `PipelineConfig.output_hash`, so upgrading does not redo
#: finished frames.
ADDED_SETTINGS_OFF = {("snap", "depth_edge_max_range"): None, ("upsample", "oversample"): 1,
                      ("upsample", "offset_scale"): 1.0}


class PipelineConfig(_Section):
    """Every setting of a run: each stage's `Options` (their defaults are the product's), the
    output folder and the cluster."""

    input: LoadOptions = Field(default_factory=LoadOptions)
    ground: GroundOptions = Field(default_factory=GroundOptions)
    tile: TileOptions = Field(default_factory=TileOptions)
    upsample: UpsampleOptions = Field(default_factory=UpsampleOptions)
    stitch: StitchOptions = Field(default_factory=StitchOptions)
    snap: SnapOptions = Field(default_factory=SnapOptions)
    fill: FillOptions = Field(default_factory=FillOptions)
    output: OutputConfig = Field(default_factory=OutputConfig)
    dask: DaskConfig = Field(default_factory=DaskConfig)
    finetune: FinetuneConfig = Field(default_factory=FinetuneConfig)

    def output_hash(self, legacy: bool = False) -> str:
        """sha256 (16 hex digits) of the settings that change the output points
        (`output_settings`), with `OUTPUT_VERSION`.

        `legacy`: the hash as versions before this one computed it, with the weights' name and the
        engine as written; a run takes the frames those wrote under it for its own.
        """
        relevant = {**self.output_settings(legacy), "output_version": OUTPUT_VERSION}
        text = json.dumps(relevant, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def output_settings(self, legacy: bool = False) -> dict[str, Any]:
        """The settings that change the output points, by section, as JSON-ready values.

        Input location, output location and cluster settings are left out: moving a run or
        changing worker counts does not change a frame's result. So is the weights file's name:
        the model is known by its checksum, which a resumed run compares apart
        (`pipeline.resume.decide`), so a copy of a file, or a file named by another path, hashes as
        the file does; and engine "auto" is given as the engine it runs where that is always eager.
        Settings added since outputs were written are left out at the value that gives the output
        of before (`ADDED_SETTINGS_OFF`). `legacy`: see `output_hash`.
        """
        dumped = self.model_dump(mode="json")
        relevant = {key: dumped[key] for key in OUTPUT_SECTIONS}
        # what load drops changes the points; where the scans are and which frames are taken do not
        relevant["input"] = {key: dumped["input"][key] for key in INPUT_POINT_KEYS}
        relevant["upsample"].pop("batch_size", None)
        relevant["upsample"].pop("device", None)
        if not legacy:
            from cadpu.inference import AUTO_ENGINES

            relevant["upsample"].pop("weights", None)
            if relevant["upsample"]["engine"] == "auto" and AUTO_ENGINES == ("eager",):
                relevant["upsample"]["engine"] = "eager"
        for (section, key), off in ADDED_SETTINGS_OFF.items():
            if relevant[section].get(key) == off:
                del relevant[section][key]
        if relevant["snap"].get("depth_edges") != "half-gap":  # the limit applies to the half-gap rule only
            relevant["snap"].pop("depth_edge_max_range", None)
        return relevant

    def to_yaml(self) -> str:
        """The resolved configuration as YAML (what `kitti-pu config` prints)."""
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)


def _deep_merge(base: dict[str, Any], update: dict[str, Any]) -> dict[str, Any]:
    merged = dict(base)
    for key, value in update.items():
        if isinstance(value, dict) and isinstance(merged.get(key), dict) and key != "params":
            merged[key] = _deep_merge(merged[key], value)
        elif isinstance(value, dict) and isinstance(merged.get(key), dict):
            merged[key] = {**merged[key], **value}
        else:
            merged[key] = value
    return merged


def _dotted_to_nested(overrides: dict[str, Any]) -> dict[str, Any]:
    """{"tile.overlap": 1} -> {"tile": {"overlap": 1}}. ConfigError when a key sets a section
    (or a setting) to a value and another key sets a setting inside it."""
    nested: dict[str, Any] = {}
    for dotted, value in overrides.items():
        parts = dotted.split(".")
        node = nested
        for depth, part in enumerate(parts[:-1]):
            node = node.setdefault(part, {})
            if not isinstance(node, dict):  # a TypeError traceback, exit 1, before
                raise ConfigError(f"--set {dotted}: {'.'.join(parts[:depth + 1])} is set to {node!r} by another "
                                  "--set; give it settings, not a value")
        node[parts[-1]] = value
    return nested


#: The repository's configuration folder: its pipeline presets (`unordered_scans.yaml`, ...) are
#: given to `-c` by name (`config_file`). An editable install, as the README's, finds it here.
CONFIGS_DIR = Path(__file__).resolve().parents[1] / "configs"
#: The file in `CONFIGS_DIR` that holds the defaults themselves: `-c` finds it, but it is no preset.
DEFAULTS_FILE = "pipeline.yaml"


def config_file(path: Path | str) -> Path:
    """The YAML file `path` names: the path itself, or for a bare name that is not a file here
    ("unordered_scans", "unordered_scans.yaml", "configs/unordered_scans.yaml"), the preset of
    that name in `CONFIGS_DIR`; the path as it is when neither exists (`read_yaml` says so)."""
    path = Path(path)
    if path.exists() or path.is_absolute():
        return path
    if len(path.parts) == 1 or (len(path.parts) == 2 and path.parts[0] == CONFIGS_DIR.name):
        preset = CONFIGS_DIR / (path.name if path.suffix in (".yaml", ".yml") else f"{path.name}.yaml")
        if preset.is_file():
            return preset
    return path


def presets() -> list[str]:
    """The names `-c` takes as presets: the pipeline configurations in `CONFIGS_DIR` (the
    training recipes there, train*.yaml, are `cadpu.train`'s; `DEFAULTS_FILE` changes nothing)."""
    if not CONFIGS_DIR.is_dir():
        return []
    return sorted(f.stem for f in CONFIGS_DIR.glob("*.yaml")
                  if not f.stem.startswith("train") and f.name != DEFAULTS_FILE)


def read_yaml(path: Path | str) -> dict[str, Any]:
    """Read one YAML override file (a path, or a preset's name: `config_file`); raises
    ConfigError naming the file when it is unreadable."""
    path = config_file(path)
    if path.is_dir():
        raise ConfigError(f"config file {path}: is a folder, not a YAML file")
    if not path.is_file():
        names = presets()
        known = f" (nor a preset; presets: {', '.join(names)})" if names and len(path.parts) == 1 else ""
        raise ConfigError(f"config file {path}: not found{known}")
    try:
        data = yaml_text.read_yaml(path.read_text(encoding="utf-8")) or {}
    except UnicodeDecodeError as error:
        raise ConfigError(f"config file {path}: not UTF-8 text (byte {error.start}); a YAML file is text") from None
    except yaml.YAMLError as error:
        raise ConfigError(f"config file {path}: not valid YAML {yaml_text.describe_error(error)}") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path}: the top level must be a mapping of sections")
    # a section whose settings are all commented out reads as None: an empty section
    return {section: {} if settings is None else settings for section, settings in data.items()}


def load_config(
    files: list[Path] | tuple[Path, ...] | Path | str = (), overrides: dict[str, Any] | None = None,
    settings: dict[str, Any] | None = None,
) -> PipelineConfig:
    """Build the configuration: defaults <- each YAML file in order <- dotted-key overrides
    <- dotted-key settings.

    Args:
        files: YAML files (or one), each a mapping of sections (input, ground, tile, upsample,
            stitch, snap, fill, output, dask) to settings.
        overrides: dotted keys to values, e.g. {"upsample.ratio": 16, "output.dir": "out"};
            None values are ignored (an option the user did not give).
        settings: dotted keys to values set explicitly (`--set`); None is a value here
            (`--set upsample.batch_size=null` restores the automatic batch size).

    Returns:
        The validated `PipelineConfig`.

    Raises:
        ConfigError: naming the file and key of the first problem found.
    """
    merged: dict[str, Any] = {}
    sources: list[tuple[str, dict[str, Any]]] = []  # (name, its settings), in the order applied
    if isinstance(files, (str, Path)):  # one file, not its characters (read as files "c", ".", ...)
        files = [files]
    for path in files:
        sources.append((str(path), read_yaml(path)))
    given = {key: value for key, value in (overrides or {}).items() if value is not None}
    given.update(settings or {})
    if given:
        sources.append(("command-line options", _dotted_to_nested(given)))
    for _, layer in sources:
        merged = _deep_merge(merged, layer)
    try:
        return PipelineConfig.model_validate(merged)
    except pydantic.ValidationError as error:
        problems, origins = [], []
        for item in error.errors():
            key = ".".join(str(part) for part in item["loc"])
            message = item["msg"].removeprefix("Value error, ")
            if item["type"] == "extra_forbidden":
                message = (f"unknown key (now {RENAMED_KEYS[key]})" if key in RENAMED_KEYS else
                           f"unknown key (did you mean {near[0]}?)" if (near := difflib.get_close_matches(
                               key, setting_keys(), n=1, cutoff=0.8)) else "unknown key")
            elif item["type"] in ("literal_error", "enum") and "input" in item:  # what was given, beside what may be
                message = f"{message}, got {item['input']!r}"
            problems.append(f"{key}: {message}" if key else message)
            origins.append(_origin(item["loc"], sources))
        origin = " + ".join(dict.fromkeys(origins)) or "defaults"
        raise ConfigError(f"bad configuration ({origin}): " + "; ".join(problems)) from None


def setting_keys(model: type[pydantic.BaseModel] | None = None, prefix: str = "") -> list[str]:
    """Every dotted key of the configuration, sections too ("tile", "tile.overlap", ...): what an
    unknown key is matched against for a suggestion."""
    keys = []
    for name, field in (model or PipelineConfig).model_fields.items():
        kind = field.annotation
        keys.append(f"{prefix}{name}")
        if isinstance(kind, type) and issubclass(kind, pydantic.BaseModel):
            keys += setting_keys(kind, f"{prefix}{name}.")
    return keys


def _origin(location: tuple, sources: list[tuple[str, dict[str, Any]]]) -> str:
    """The name of the last source that sets the deepest part of `location` (a key path of a
    validation error), or "defaults" when none sets any of it."""
    for depth in range(len(location), 0, -1):
        for name, layer in reversed(sources):
            node: Any = layer
            for part in location[:depth]:
                node = node.get(part, _MISSING) if isinstance(node, dict) else _MISSING
            if node is not _MISSING:
                return name
    return "defaults"


_MISSING = object()


def absolute(path: str | Path) -> Path:
    """`path` with `~` expanded and made absolute, its leading `..` folded into the working folder
    ("../out" from /a/b is /a/out, not /a/b/../out, in the summary and its messages). The working
    folder is already free of links, so that folding is exact; a `..` after another folder, which
    may be a link, is left for the file system to follow."""
    path = Path(path).expanduser()
    if path.is_absolute():
        return path
    ups = next((i for i, part in enumerate(path.parts) if part != ".."), len(path.parts))
    if ".." in path.parts[ups:]:
        return path.absolute()
    base = Path.cwd()
    for _ in range(ups):
        base = base.parent
    return base.joinpath(*path.parts[ups:])
