"""The install-time hook that makes a plain `import open3d` work (setup.py, `kitti_pu_open3d.pth`).

The wheels are built with the project's real setup.py and pyproject.toml through the setuptools
backend that pyproject.toml names, from a copy of the build files with empty packages (so that the
build does not copy the weights or write into the checkout). The hook itself runs in a fresh
interpreter through `site.addsitedir`, which processes `.pth` files as interpreter start does.
"""

from __future__ import annotations

import json
import shutil
import site
import subprocess
import sys
import zipfile
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PTH_NAME = "kitti_pu_open3d.pth"
HOOK_CLASS = "KittiPuOpen3dLibusb"


def _build(kind: str, tmp_path: Path) -> zipfile.ZipFile:
    """Build the project's `kind` wheel ("wheel" or "editable") and open it."""
    project = tmp_path / "project"
    project.mkdir()
    for name in ("pyproject.toml", "setup.py", "README.md"):
        shutil.copy(ROOT / name, project / name)
    for package in ("cadpu", "stages", "pipeline"):
        (project / package).mkdir()
        (project / package / "__init__.py").write_text("")
    dist = tmp_path / "dist"
    code = f"import sys; from setuptools import build_meta; print(build_meta.build_{kind}(sys.argv[1]))"
    done = subprocess.run([sys.executable, "-c", code, str(dist)], cwd=project, capture_output=True,
                          text=True, timeout=120)
    assert done.returncode == 0, done.stderr
    return zipfile.ZipFile(dist / done.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("kind", ["wheel", "editable"])
def test_regular_and_editable_wheels_install_the_hook_into_site_packages(kind: str, tmp_path: Path) -> None:
    with _build(kind, tmp_path) as wheel:
        names = wheel.namelist()
        record = next(name for name in names if name.endswith(".dist-info/RECORD"))
        assert PTH_NAME in names  # the wheel's root is site-packages once installed
        assert any(line.startswith(PTH_NAME + ",") for line in wheel.read(record).decode().splitlines())
        line = wheel.read(PTH_NAME).decode()
    assert line.startswith("import ") and line.count("\n") == 1  # one line that site executes


# Runs the hook as interpreter start would, then a plain `import open3d`; prints what it saw.
HOOK_RUN = f"""
import json, site, sys
sys.meta_path[:] = [f for f in sys.meta_path if getattr(f, "__name__", "") != "{HOOK_CLASS}"]
before = set(sys.modules)
site.addsitedir(sys.argv[1])
hooks = [f for f in sys.meta_path if getattr(f, "__name__", "") == "{HOOK_CLASS}"]
imported_at_start = sorted(set(sys.modules) - before)
first = sys.meta_path.index(hooks[0]) if hooks else None
import open3d
print(json.dumps({{
    "hooks": len(hooks), "first": first,
    "imported_at_start": imported_at_start, "preloaded": "cadpu._libusb" in sys.modules,
    "hook_left": any(getattr(f, "__name__", "") == "{HOOK_CLASS}" for f in sys.meta_path),
    "open3d": open3d.__version__}}))
"""


def test_the_hook_imports_nothing_at_start_and_preloads_libusb_on_the_first_import_of_open3d(
        tmp_path: Path) -> None:
    with _build("editable", tmp_path) as wheel:
        site_dir = tmp_path / "site"
        site_dir.mkdir()
        (site_dir / PTH_NAME).write_bytes(wheel.read(PTH_NAME))
    done = subprocess.run([sys.executable, "-c", HOOK_RUN, str(site_dir)], capture_output=True, text=True,
                          env={"PYTHONPATH": str(ROOT), "PATH": "/usr/bin:/bin"}, timeout=120)
    assert done.returncode == 0, done.stderr
    seen = json.loads(done.stdout.strip().splitlines()[-1])
    assert seen["hooks"] == 1 and seen["first"] == 0
    assert seen["imported_at_start"] == []
    assert seen["preloaded"] and not seen["hook_left"]


def test_the_hook_never_raises_when_cadpu_cannot_be_imported(tmp_path: Path) -> None:
    with _build("wheel", tmp_path) as wheel:
        site_dir = tmp_path / "site"
        site_dir.mkdir()
        (site_dir / PTH_NAME).write_bytes(wheel.read(PTH_NAME))
    code = ("import site, sys\nsite.addsitedir(sys.argv[1])\n"
            "try:\n    import open3d\nexcept ImportError as error:\n    print(error)\n"
            "print('cadpu' in sys.modules)\n")
    # cadpu is not importable: `-I` leaves the checkout off the path and ignores PYTHONPATH.
    done = subprocess.run([sys.executable, "-I", "-S", "-c", code, str(site_dir)], capture_output=True,
                          text=True, cwd=tmp_path, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stderr == ""
    # Open3D's own error (not on this path), not the hook's failure to import cadpu.
    assert done.stdout.splitlines() == ["No module named 'open3d'", "False"]


def test_this_environment_has_the_hook_and_a_plain_import_of_open3d_works(tmp_path: Path) -> None:
    installed = [Path(folder, PTH_NAME) for folder in site.getsitepackages() if Path(folder, PTH_NAME).is_file()]
    assert installed, (
        f"{PTH_NAME} is not installed: this environment's kitti-pu predates it; reinstall with "
        "`pip install -e \".[test]\"`")
    code = "import sys, open3d; print('cadpu' in sys.modules)"
    # An empty folder as cwd (first on the child's path): neither the source tree nor stray files
    # beside the checkout (a scratch `select.py` once shadowed the standard library) are imported.
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, cwd=tmp_path,
                          env={"PATH": "/usr/bin:/bin"}, timeout=120)
    assert done.returncode == 0, done.stderr
    assert done.stdout.strip() == "True"  # the hook's preload ran before Open3D's import
