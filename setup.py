"""The one build step that pyproject.toml cannot declare: Open3D's libusb start-up hook.

Open3D (the `open3d` extra) links `libusb-1.0.so.0`, which bare machines lack. `cadpu._libusb`
makes it loadable (the system's copy when present, else the one the extra's `libusb-package`
ships, loaded with RTLD_GLOBAL), and importing the `cadpu` package runs it. So that a plain
`import open3d` works too, in a process that imports no kitti-pu package, the build places
`kitti_pu_open3d.pth` at the root of the wheel, which is site-packages once installed, for a
regular and an editable install alike.

Python executes a `.pth` line that starts with "import" at every interpreter start, so the line
does as little as it can: it puts a finder in front of `sys.meta_path` (no import, no library
load; docs/results.md has the measured start-up cost). The finder acts once, when `open3d` is
first imported: it takes itself off `sys.meta_path`, calls `cadpu._libusb.preload_libusb` and
returns None, so the ordinary finders import Open3D. It never raises: if anything fails, Open3D's
import goes on and reports its own error, as it would without it.

Where the file goes: for a regular wheel (`pip install .`) into build_lib, which becomes the
wheel's root. For an editable wheel (`pip install -e .`, PEP 660) setuptools' editable_wheel packs
its own path finder, not build_lib, but points the `install` command's install_lib at the root of
the wheel it builds (where it also puts scripts and data files), so the file goes there.
tests/test_packaging.py builds both kinds and checks the file and what it does.
"""

from __future__ import annotations

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

PTH_NAME = "kitti_pu_open3d.pth"

# Run with its own globals, holding only `sys`; source kept short because it is compiled at
# every interpreter start.
HOOK_SOURCE = """\
class KittiPuOpen3dLibusb:
    @classmethod
    def find_spec(cls, name, path=None, target=None):
        if name == "open3d":
            try:
                sys.meta_path.remove(cls)
            except ValueError:
                pass
            try:
                from cadpu._libusb import preload_libusb
                preload_libusb()
            except Exception:
                pass
        return None
if "open3d" not in sys.modules:
    sys.meta_path.insert(0, KittiPuOpen3dLibusb)
"""

PTH_LINE = (
    "import sys; exec(" + repr(HOOK_SOURCE) + ", {'sys': sys, '__name__': 'kitti_pu_open3d_pth'})\n"
)


class BuildPyWithPth(build_py):
    """build_py that also writes `kitti_pu_open3d.pth` at the root of the wheel being built."""

    def run(self) -> None:
        super().run()
        Path(self._pth_dir(), PTH_NAME).write_text(PTH_LINE, encoding="utf-8")

    def _pth_dir(self) -> str:
        if getattr(self, "editable_mode", False):
            return self.get_finalized_command("install").install_lib
        return self.build_lib

    def get_outputs(self, include_bytecode: bool = True) -> list[str]:
        outputs = super().get_outputs(include_bytecode)
        if not getattr(self, "editable_mode", False):
            outputs.append(str(Path(self.build_lib, PTH_NAME)))
        return outputs


setup(cmdclass={"build_py": BuildPyWithPth})
