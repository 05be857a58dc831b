"""Make a plain `import open3d` work in a kitti-pu environment without the system libusb.

Open3D's pip wheel links `libusb-1.0.so.0`, which bare machines lack; `cadpu._libusb` loads the
copy that the `libusb-package` dependency ships. The build (setup.py) installs
`kitti_pu_open3d.pth` beside this module in site-packages, for a regular and an editable
install alike; its one line calls `install()` at every interpreter start.

`install()` only puts a finder at the front of `sys.meta_path`: no import, no library load, so
interpreter start-up stays as fast as it was (docs/results.md has the measured cost). The finder
acts once, when `open3d` is first imported: it removes itself, imports `cadpu._libusb` (whose
package import preloads libusb: the system's when present, else libusb-package's, with
RTLD_GLOBAL) and lets the ordinary finders import Open3D. It never raises: if anything fails,
Open3D's import goes on and fails with its own message, as it would without the hook.
"""

from __future__ import annotations

import sys
from importlib.machinery import ModuleSpec
from typing import Sequence


class PreloadLibusbFinder:
    """A `sys.meta_path` finder that finds nothing: it preloads libusb before `open3d` imports."""

    @classmethod
    def find_spec(cls, name: str, path: Sequence[str] | None = None, target: object = None) -> ModuleSpec | None:
        """Preload libusb when `name` is `open3d`, then return None (the usual finders import it)."""
        if name == "open3d":
            uninstall()
            try:
                import cadpu._libusb  # noqa: F401  (importing the cadpu package preloads libusb)
            except Exception:  # noqa: BLE001  (never break an import: Open3D then reports its own error)
                pass
        return None


def install() -> None:
    """Put the finder at the front of `sys.meta_path` (once; a no-op if Open3D is already imported)."""
    if "open3d" not in sys.modules and PreloadLibusbFinder not in sys.meta_path:
        sys.meta_path.insert(0, PreloadLibusbFinder)


def uninstall() -> None:
    """Take the finder off `sys.meta_path`, if it is there."""
    while PreloadLibusbFinder in sys.meta_path:
        sys.meta_path.remove(PreloadLibusbFinder)
