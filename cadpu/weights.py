"""Weight files of the generator: save, checksum, load.

A weight file is `torch.save({"state_dict", "config", "meta"})`; next to it, `<file>.sha256` holds
its SHA-256. Loading checks the checksum first when that file is there (`save` writes it; the
shipped files have it), so a truncated or altered file is reported instead of silently producing
garbage; a weights file copied without it loads unchecked, and its own SHA-256 is still what runs
record.
"""

from __future__ import annotations

import hashlib
import io
import json
import os
import uuid
import zipfile
from pathlib import Path
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:  # torch is imported where a file is read or written: the path helpers here need
    # none of it, and resolving a run's paths loaded it (1.2 s) before a missing input was said
    import torch

    from .network import Generator

WEIGHTS_DIR = Path(__file__).parent / "weights"
#: The shipped model (curvature-adaptive expansion, alpha = 0.5) and its alpha = 1.0 ablation.
DEFAULT_WEIGHTS = WEIGHTS_DIR / "cadpu_r4.pt"
UNIFORM_WEIGHTS = WEIGHTS_DIR / "cadpu_r4_alpha1.pt"
#: The pair trained on simulated 16-of-64-ring street scans only (configs/train_lidar*.yaml).
LIDAR_WEIGHTS = WEIGHTS_DIR / "cadpu_r4_lidar.pt"
LIDAR_UNIFORM_WEIGHTS = WEIGHTS_DIR / "cadpu_r4_lidar_alpha1.pt"
#: Each shipped file and its twin: the file trained on the same data with the other alpha (0.5 <-> 1.0).
TWINS = {DEFAULT_WEIGHTS: UNIFORM_WEIGHTS, UNIFORM_WEIGHTS: DEFAULT_WEIGHTS,
         LIDAR_WEIGHTS: LIDAR_UNIFORM_WEIGHTS, LIDAR_UNIFORM_WEIGHTS: LIDAR_WEIGHTS}


class WeightsError(RuntimeError):
    """A weights file is missing, corrupt, non-finite, or does not match its checksum."""


def sha256_of(path: Path) -> str:
    """Hex SHA-256 of a file's bytes."""
    return hashlib.sha256(Path(path).read_bytes()).hexdigest()


def save(generator: Generator, path: Path, meta: dict[str, Any] | None = None) -> str:
    """Write `generator`'s weights to `path` (atomically) and its checksum to `path.sha256`.

    Returns:
        The file's SHA-256.

    Raises:
        ValueError naming the tensor when a weight is NaN or infinite (a diverged run): such a
        file would be refused at every load, so none is written.
    """
    path = Path(path)
    state = {k: v.detach().cpu() for k, v in generator.state_dict().items()}
    found = non_finite(state)
    if found is not None:
        raise ValueError(f"{path}: not written: {found[1]} non-finite values (NaN or infinite) in {found[0]}")
    return write_file(path, state, generator.config, meta)


def non_finite(state: dict[str, torch.Tensor]) -> tuple[str, int] | None:
    """The first tensor of a state dict holding NaN or infinite values, and how many, or None."""
    import torch

    for name, tensor in state.items():
        if tensor.is_floating_point() and not bool(torch.isfinite(tensor).all()):
            return name, int((~torch.isfinite(tensor)).sum())
    return None


def write_file(path: Path, state: dict[str, torch.Tensor], config: dict[str, Any],
               meta: dict[str, Any] | None = None) -> str:
    """Write a weights file of `state` (a generator's state dict, CPU tensors) and `config` to
    `path` (atomically) and its checksum to `path.sha256`, the values unchecked (`save` checks
    them first; the tests write damaged files with this). Returns the file's SHA-256."""
    import torch

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    buffer = io.BytesIO()
    # Plain JSON types only, so the file loads with torch.load(weights_only=True).
    plain_meta = json.loads(json.dumps(meta or {}, default=str))
    torch.save({"state_dict": state, "config": config, "meta": plain_meta}, buffer)
    data = buffer.getvalue()
    digest = hashlib.sha256(data).hexdigest()
    for target, content in ((path, data), (Path(f"{path}.sha256"), f"{digest}  {path.name}\n".encode())):
        temporary = target.with_name(f".{target.name}.tmp-{uuid.uuid4().hex[:8]}")
        try:
            temporary.write_bytes(content)
            os.replace(temporary, target)
        finally:
            temporary.unlink(missing_ok=True)  # left only when the write or the rename failed
    return digest


def check_weights_target(path: Path | str, option: str, shipped_allowed: bool = True) -> Path:
    """`path` as a place `save` can write a weights file, checked before a training run spends its
    time. Returns the path.

    Args:
        path: the weights file to write. option: how the caller's user gives it, for messages.
        shipped_allowed: False refuses a path in the package's folder of shipped files (a fine-tuned
            file written there replaced a shipped one, checksum and all: a trial).

    Raises:
        ValueError naming `option` when the path or its `.sha256` is a folder, a part of the folder
        it would go in is a file, or an existing file there is not a weights file (a training
        checkpoint, or anything else: `save` would replace it).
    """
    path = Path(path)
    for target in (path, Path(f"{path}.sha256")):
        if target.is_dir():
            raise ValueError(f"{option}: {target} is a folder; give the weights file's path (e.g. {target / 'generator.pt'})")
    blocking = next((part for part in path.parents if part.exists() and not part.is_dir()), None)
    if blocking is not None:
        raise ValueError(f"{option}: {path} cannot be written: {blocking} is a file, not a folder")
    # the folder itself, not where a link named `path` points: writing replaces the link
    parent = path.absolute().parent
    if not shipped_allowed and parent.is_dir() and os.path.samefile(parent, WEIGHTS_DIR):
        raise ValueError(f"{option}: {path} is in the folder of the weights shipped with kitti-pu ({WEIGHTS_DIR}), "
                         "which holds those alone; write the file elsewhere")
    if path.is_file() and path.stat().st_size and not is_weights_file(path):  # an empty placeholder may go
        what = "a training checkpoint, which it would destroy" if is_training_checkpoint(path) else "not a weights file"
        raise ValueError(f"{option}: {path} exists and is {what}; give another file (an existing weights file "
                         "is replaced)")
    return path


def shipped_names() -> list[str]:
    """Names of the weight files shipped in the package (file names without `.pt`)."""
    return sorted(path.stem for path in WEIGHTS_DIR.glob("*.pt"))


def portable_name(weights: Path | str) -> str:
    """How to name a weights file so that any installation and any folder find it: a shipped file
    by its name, however it is given (its name, its path, a link to it), any other by its absolute
    path (`weights` itself when it names no shipped file; `resolve` reads it either way)."""
    path = resolve(weights).expanduser()
    real = path.resolve()
    if real.is_file() and real.parent == WEIGHTS_DIR.resolve() and real.suffix == ".pt":
        return real.stem
    return str(path.absolute())


def twin(path: Path | str | None) -> Path | None:
    """The ablation partner of a shipped weights file: the one trained on the same data with the
    other alpha (`TWINS`; None means DEFAULT_WEIGHTS); None for any other file. A shipped file is
    known by its path, relative or not, or by its content (a copy, or another checkout's): given as
    `cadpu/weights/cadpu_r4.pt` it was taken for a file of one's own, and compared with itself."""
    given = resolve(path)
    by_path = {Path(os.path.realpath(shipped)): partner for shipped, partner in TWINS.items()}
    partner = by_path.get(Path(os.path.realpath(given)))
    if partner is not None:
        return partner
    if not given.is_file():
        return None
    checksum = sha256_of(given)
    return next((partner for shipped, partner in TWINS.items() if sha256_of(shipped) == checksum), None)


def resolve(path: Path | str | None) -> Path:
    """A weights file from a path or from the name of a shipped file ("cadpu_r4_lidar").

    A bare name that is not a file here names a shipped file, with or without its ".pt"
    ("cadpu_r4_lidar.pt"); None is DEFAULT_WEIGHTS.
    """
    if path is None:
        return DEFAULT_WEIGHTS
    candidate = Path(path)
    if not candidate.exists() and candidate.name == str(path) and candidate.suffix in ("", ".pt"):
        shipped = WEIGHTS_DIR / f"{candidate.stem if candidate.suffix else candidate}.pt"
        if shipped.is_file():
            return shipped
    return candidate


def is_training_checkpoint(path: Path) -> bool:
    """Whether a file is a checkpoint of `cadpu.train` (its pickle names the optimiser states),
    told without unpickling it: checkpoints hold more than tensors, and are never loaded as weights."""
    pickled = _pickled(path)
    return b"opt_g" in pickled and b"discriminator" in pickled


def is_weights_file(path: Path) -> bool:
    """Whether a file is laid out as `write_file` writes weights: a torch file of tensors and plain
    values (read with `weights_only`, which never runs a pickle's code) holding the state dict, the
    config and the meta; its contents are not checked (`load_generator`)."""
    import torch

    if not zipfile.is_zipfile(path):
        return False
    try:
        saved = torch.load(path, map_location="cpu", weights_only=True)
    except Exception:  # noqa: BLE001 (anything that does not read so is not a weights file)
        return False
    return isinstance(saved, dict) and {"state_dict", "config", "meta"} <= saved.keys()


def _pickled(path: Path) -> bytes:
    """The pickle of a torch archive (its `data.pkl`), b"" for a file that is not one."""
    try:
        with zipfile.ZipFile(path) as archive:
            return next((archive.read(name) for name in archive.namelist() if name.endswith("data.pkl")), b"")
    except (zipfile.BadZipFile, OSError):
        return b""


def load_generator(path: Path | str | None = None, map_location: str = "cpu") -> tuple[Generator, str, dict]:
    """Load a generator from a weights file, checking its checksum when `<file>.sha256` is beside it.

    Args:
        path: weights file, or the name of a shipped one (`resolve`); None loads DEFAULT_WEIGHTS.

    Returns:
        (generator in eval mode, sha256 of the file, the file's meta dict).

    Raises:
        WeightsError: naming the file, when it is missing, unreadable, fails its checksum, does
            not hold a CAD-PU generator, or holds a NaN or infinite parameter.
    """
    path = resolve(path)
    if path.is_dir():
        raise WeightsError(f"{path}: a folder, not a weights file (e.g. {path / 'generator.pt'})")
    if not path.is_file():
        raise WeightsError(f"{path}: weights file not found (shipped names: {', '.join(shipped_names())})")
    digest = sha256_of(path)
    checksum_file = Path(f"{path}.sha256")
    if checksum_file.is_file():
        written = checksum_file.read_text(errors="replace").split()
        if not written:
            raise WeightsError(f"{path}: its checksum file {checksum_file.name} is empty; write it again "
                               f"(sha256sum) or remove it")
        if written[0] != digest:
            raise WeightsError(f"{path}: checksum mismatch (file {digest[:12]}, {checksum_file.name} "
                               f"{written[0][:12]}); the file is corrupt or was replaced")
    import torch

    from .network import Generator

    try:
        saved = torch.load(path, map_location=map_location, weights_only=True)
        generator = Generator(**saved["config"])
        generator.load_state_dict(saved["state_dict"])
    except Exception as error:  # any unpickling / shape problem means the file is not usable
        if is_training_checkpoint(path):
            if Path(path).parent.name.endswith(".run"):  # `kitti-pu finetune --out FILE` keeps it in FILE.run/
                weights_file = Path(path).parent.with_name(Path(path).parent.name.removesuffix(".run"))
                raise WeightsError(f"{path}: the checkpoint of a `kitti-pu finetune` run (which continues it with "
                                   f"--resume), not a weights file; the run writes its weights to {weights_file}, "
                                   "its --out") from None
            raise WeightsError(f"{path}: a training checkpoint of `python -m cadpu.train` (which continues it "
                               "with --resume), not a weights file; a run writes its weights to generator.pt "
                               "in its output folder, or to --weights-out") from None
        if "Weights only load failed" in str(error):  # torch's text here is a paragraph about weights_only
            reason = "not a torch file of tensors and plain values; a file holding anything else is never unpickled"
        elif not zipfile.is_zipfile(path):  # torch's texts: "KeyError: 101", a miniz error paragraph
            reason = "not a torch file, or one cut short"
        else:
            reason = f"{type(error).__name__}: {str(error).strip().splitlines()[0] if str(error).strip() else ''}"
        raise WeightsError(f"{path}: not a CAD-PU weights file ({reason})") from None
    found = non_finite(generator.state_dict())
    if found is not None:
        raise WeightsError(f"{path}: {found[1]} non-finite values (NaN or infinite) in {found[0]}; the "
                           "training run that saved it diverged")
    return generator.eval(), digest, dict(saved.get("meta", {}))
