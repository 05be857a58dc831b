"""The pipeline's typed configuration: defaults here, overridden by YAML files and CLI options.

One `PipelineConfig` holds every setting. `load_config` merges, in order, the defaults, any number
of YAML files and a dict of dotted-key overrides (``{"upsample.ratio": 8}``), then validates the
result. Unknown keys and bad values raise `ConfigError` with a message naming the key.
"""

from __future__ import annotations

import dataclasses
import hashlib
import json
from pathlib import Path
from typing import Any, Literal

import pydantic
import yaml
from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

GROUND_METHODS = ("patchwork", "ransac", "patchworkpp")


class ConfigError(ValueError):
    """A configuration file, key or value is invalid; the message names it."""


class _Section(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class InputConfig(_Section):
    """Where the scans are.

    path: a raw drive, a raw date folder, a raw base, an odometry base or sequence folder, a folder
        of .bin files, or a base folder with any of these under it.
    kind: "auto" recognises the layout; "raw", "odometry" or "bin" forces it.
    sequences: drive names or sequence ids to take (all when None).
    first_frame / last_frame / step: frame range, last_frame inclusive (None = to the end).
    """

    path: Path | None = None
    kind: Literal["auto", "raw", "odometry", "bin"] = "auto"
    sequences: list[str] | None = None
    first_frame: int = Field(0, ge=0)
    last_frame: int | None = Field(None, ge=0)
    step: int = Field(1, ge=1)
    max_points: int = Field(1_000_000, ge=1)

    @model_validator(mode="after")
    def _check_range(self) -> "InputConfig":
        if self.last_frame is not None and self.last_frame < self.first_frame:
            raise ValueError(
                f"input.last_frame ({self.last_frame}) is before input.first_frame ({self.first_frame})"
            )
        return self

    def frame_range(self) -> range | None:
        """The selected frame indices as a range, or None for all frames."""
        if self.first_frame == 0 and self.last_frame is None and self.step == 1:
            return None
        stop = (self.last_frame + 1) if self.last_frame is not None else 10**9
        return range(self.first_frame, stop, self.step)


class GroundConfig(_Section):
    """Ground removal: the method and its parameters (see `stages.ground`)."""

    method: Literal["patchwork", "ransac", "patchworkpp"] = "patchwork"
    params: dict[str, Any] = Field(default_factory=dict)

    @model_validator(mode="after")
    def _check_params(self) -> "GroundConfig":
        _validate_stage_params(self.method, self.params)
        return self


class TileConfig(_Section):
    """Tiling of the non-ground points into patches (see `stages.tile`)."""

    method: Literal["partition", "fps"] = "partition"
    patch_size: int = Field(256, ge=16)
    #: 1.0: on six simulated held-out street scans and on the six real KITTI scans, voxel F1 and
    #: Chamfer distance were as good or better than with 4/3 (0.572 vs 0.563 F1 in simulation,
    #: 0.447 vs 0.444 on KITTI), with a quarter fewer patches; 2.0 was worse (0.556).
    overlap: float = Field(1.0, ge=1.0, le=8.0)
    seed: int = 0
    #: z is multiplied by this before tiling and divided by it after upsampling (`stages.tile`),
    #: so the network's copies reach across the gaps between LiDAR rings. 0.15: on six simulated
    #: held-out street scans (16 of 64 rings in) the Chamfer distance was 0.0445 m against 0.0475
    #: unscaled (0.0448 at 0.3, 0.0445 at 0.08) and voxel F1 0.611 against 0.572; 1 = no scaling.
    vertical_scale: float = Field(0.15, gt=0.0)


class UpsampleConfig(_Section):
    """The network: ratio, weights, batch size, device, and the widest patch it is given
    (`stages.upsample.run`; radius in metres after `tile.vertical_scale`; 0 = every patch).

    weights: a file, or the name of a shipped one (`cadpu.weights.resolve`). The default,
        cadpu_r4_lidar, is the curvature-adaptive network trained on simulated 16-of-64-ring
        street scans (configs/train_lidar.yaml): with ring snapping and the range check of
        `stitch`, it has the lowest Chamfer distance and highest voxel F1 of the shipped files
        on the 16-to-64-beam evaluation (cadpu/MODEL_CARD.md). cadpu_r4 is the object-level model.
    max_patch_radius: 0 (every patch). With `stitch.range_tolerance` dropping the generated
        points that do not fit the scan's rings, upsampling the wide far patches too gave the
        lowest Chamfer distance on six simulated held-out streets (bench/simulated_scans.py:
        0.0370 m against 0.0393 at 6 m and 0.0375 at 12 m; F1 0.727, 0.720, 0.731).
    """

    ratio: int = Field(4, ge=2, le=64)
    weights: Path | None = Path("cadpu_r4_lidar")
    batch_size: int | None = Field(None, ge=1)
    device: str = "auto"
    seed: int = 0
    max_patch_radius: float = Field(0.0, ge=0)

    @property
    def patch_radius_limit(self) -> float | None:
        """`max_patch_radius` as `stages.upsample.run` takes it: None for 0 (no limit)."""
        return self.max_patch_radius or None

    @field_validator("device")
    @classmethod
    def _check_device(cls, value: str) -> str:
        if value not in ("auto", "cpu") and not value.startswith("cuda"):
            raise ValueError(f"upsample.device must be 'auto', 'cpu' or 'cuda[:N]', got {value!r}")
        return value


class StitchConfig(_Section):
    """What goes into the output cloud besides the generated points, and where those lie.

    snap_to_rings: move every generated point, at its azimuth and range, onto the nearest of the
        r - 1 virtual laser rings between the two real rings it lies between, and drop generated
        points above the top or below the bottom ring (`stages.ring_snap`). Needs the scan in its
        stored ring-by-ring order (KITTI's); a frame without it is written unsnapped, with a note.
    range_tolerance: with snapping, also drop generated points whose range does not fit the two
        real returns above and below them in their azimuth column, give or take this many metres
        (`stages.ring_snap.fits_ring_ranges`), and spread the points of a ring gap on one surface
        over its virtual rings (`stages.ring_snap.snap_and_check`); null does neither. 0.05 m: of
        0.03, 0.05 and 0.1 m, the lowest Chamfer distance on six simulated held-out streets
        (bench/simulated_scans.py), measured before the spreading.
    fill_ground: with keep_ground, put r - 1 points between every two neighbouring ground returns
        of an azimuth column, on the virtual rings, along the line between them
        (`stages.ground_fill`): the network densifies only the non-ground points. Needs the ring
        order too.
    Measured effect of these on the 16-to-64-beam evaluation: README, "Quality on real KITTI
    scans", and cadpu/MODEL_CARD.md, "The pipeline default on scans".
    """

    keep_ground: bool = True
    keep_input: bool = True
    snap_to_rings: bool = True
    range_tolerance: float | None = Field(0.05, ge=0)
    fill_ground: bool = True


class OutputConfig(_Section):
    """Where and how results are written."""

    dir: Path = Path("kitti-pu-out")
    formats: list[Literal["parquet", "ply"]] = Field(default_factory=lambda: ["parquet", "ply"])
    overwrite: bool = False

    @field_validator("formats")
    @classmethod
    def _check_formats(cls, value: list[str]) -> list[str]:
        if not value:
            raise ValueError("output.formats must name at least one of 'parquet', 'ply'")
        return list(dict.fromkeys(value))


class DaskConfig(_Section):
    """The cluster: a LocalCluster sized to the machine, or an existing scheduler's address.

    n_workers: worker processes of the LocalCluster (None = one per core, at most 4).
    torch_threads: torch intra-op threads per worker (None = cores / workers, at least 1).
    max_in_flight: frames submitted at once (None = 2 per worker); bounds memory.
    memory_limit: per worker of the LocalCluster, e.g. "4GiB" or "auto".
    """

    scheduler: str | None = None
    n_workers: int | None = Field(None, ge=1)
    threads_per_worker: int = Field(1, ge=1)
    torch_threads: int | None = Field(None, ge=1)
    max_in_flight: int | None = Field(None, ge=1)
    memory_limit: str = "auto"
    dashboard: bool = False


class PipelineConfig(_Section):
    """Every setting of a run."""

    input: InputConfig = Field(default_factory=InputConfig)
    ground: GroundConfig = Field(default_factory=GroundConfig)
    tile: TileConfig = Field(default_factory=TileConfig)
    upsample: UpsampleConfig = Field(default_factory=UpsampleConfig)
    stitch: StitchConfig = Field(default_factory=StitchConfig)
    output: OutputConfig = Field(default_factory=OutputConfig)
    dask: DaskConfig = Field(default_factory=DaskConfig)

    def output_hash(self) -> str:
        """sha256 (16 hex digits) of the settings that change the output points.

        Input location, output location and cluster settings are left out: moving a run or
        changing worker counts does not change a frame's result.
        """
        relevant = {
            key: self.model_dump(mode="json")[key] for key in ("ground", "tile", "upsample", "stitch")
        }
        relevant["upsample"].pop("batch_size", None)
        relevant["upsample"].pop("device", None)
        text = json.dumps(relevant, sort_keys=True)
        return hashlib.sha256(text.encode()).hexdigest()[:16]

    def to_yaml(self) -> str:
        """The resolved configuration as YAML (what `kitti-pu config` prints)."""
        return yaml.safe_dump(self.model_dump(mode="json"), sort_keys=False)


def _validate_stage_params(method: str, params: dict[str, Any]) -> None:
    """Check ground.params against the parameter dataclass of the chosen method."""
    from stages import ground

    params_class = ground.params_class(method)
    if params_class is None:
        if params:
            raise ValueError(f"ground.params: method {method!r} takes no parameters, got {sorted(params)}")
        return
    known = {f.name for f in dataclasses.fields(params_class)}
    unknown = sorted(set(params) - known)
    if unknown:
        raise ValueError(
            f"ground.params: unknown key(s) {unknown} for method {method!r}; known: {sorted(known)}"
        )
    try:
        pydantic.TypeAdapter(params_class).validate_python(params)
    except pydantic.ValidationError as error:
        first = error.errors()[0]
        key = ".".join(str(part) for part in first["loc"])
        raise ValueError(f"ground.params.{key}: {first['msg']}") from None


def ground_params(config: GroundConfig) -> Any:
    """The ground method's parameter object built from `config.params` (None if it takes none)."""
    from stages import ground

    params_class = ground.params_class(config.method)
    if params_class is None:
        return None
    return pydantic.TypeAdapter(params_class).validate_python(config.params)


def stitch_options(config: PipelineConfig) -> dict[str, Any]:
    """Keyword arguments of `stages.stitch.run` for these settings: the stitch section and the
    upsampling ratio (the ring gaps of snapping and of the ground fill)."""
    section = config.stitch
    return dict(keep_ground=section.keep_ground, keep_input=section.keep_input,
                snap_to_rings=section.snap_to_rings, range_tolerance=section.range_tolerance,
                fill_ground=section.fill_ground, ratio=config.upsample.ratio)


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
    nested: dict[str, Any] = {}
    for dotted, value in overrides.items():
        parts = dotted.split(".")
        node = nested
        for part in parts[:-1]:
            node = node.setdefault(part, {})
        node[parts[-1]] = value
    return nested


def read_yaml(path: Path) -> dict[str, Any]:
    """Read one YAML override file; raises ConfigError naming the file when it is unreadable."""
    path = Path(path)
    if not path.is_file():
        raise ConfigError(f"config file {path}: not found")
    try:
        data = yaml.safe_load(path.read_text()) or {}
    except yaml.YAMLError as error:
        raise ConfigError(f"config file {path}: not valid YAML ({error})") from None
    if not isinstance(data, dict):
        raise ConfigError(f"config file {path}: the top level must be a mapping of sections")
    return data


def load_config(
    files: list[Path] | tuple[Path, ...] = (), overrides: dict[str, Any] | None = None,
    settings: dict[str, Any] | None = None,
) -> PipelineConfig:
    """Build the configuration: defaults <- each YAML file in order <- dotted-key overrides
    <- dotted-key settings.

    Args:
        files: YAML files, each a mapping of sections (input, ground, tile, upsample, stitch,
            output, dask) to settings.
        overrides: dotted keys to values, e.g. {"upsample.ratio": 8, "output.dir": "out"};
            None values are ignored (an option the user did not give).
        settings: dotted keys to values set explicitly (`--set`); None is a value here
            (`--set upsample.batch_size=null` restores the automatic batch size).

    Returns:
        The validated `PipelineConfig`.

    Raises:
        ConfigError: naming the file and key of the first problem found.
    """
    merged: dict[str, Any] = {}
    origin = "defaults"
    for path in files:
        merged = _deep_merge(merged, read_yaml(path))
        origin = str(path)
    given = {key: value for key, value in (overrides or {}).items() if value is not None}
    given.update(settings or {})
    if given:
        merged = _deep_merge(merged, _dotted_to_nested(given))
        origin = f"{origin} + command-line options" if files else "command-line options"
    try:
        return PipelineConfig.model_validate(merged)
    except pydantic.ValidationError as error:
        problems = []
        for item in error.errors():
            key = ".".join(str(part) for part in item["loc"])
            message = item["msg"].removeprefix("Value error, ")
            if item["type"] == "extra_forbidden":
                message = "unknown key"
            problems.append(f"{key}: {message}" if key else message)
        raise ConfigError(f"bad configuration ({origin}): " + "; ".join(problems)) from None
