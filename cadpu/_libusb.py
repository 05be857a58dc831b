"""Make Open3D's `libusb-1.0.so.0` loadable without a system package (see `cadpu.o3d`).

Kept apart from `cadpu.o3d` so that importing the `cadpu` package, which calls `preload_libusb`,
does not import Open3D itself.
"""

from __future__ import annotations

import ctypes

_SONAME = "libusb-1.0.so.0"


def preload_libusb() -> bool:
    """Make `libusb-1.0.so.0` loadable for Open3D: the system's when present, else the copy in
    `libusb-package`, loaded with RTLD_GLOBAL.

    Returns True when a libusb is loaded, False when neither is available (Open3D's import then
    fails with its own message). Cheap: no import of Open3D, no subprocess.
    """
    try:
        ctypes.CDLL(_SONAME, mode=ctypes.RTLD_GLOBAL)
        return True
    except OSError:
        pass
    try:
        import libusb_package
    except ImportError:
        return False
    library = libusb_package.get_library_path()
    if library is None:
        return False
    try:
        ctypes.CDLL(str(library), mode=ctypes.RTLD_GLOBAL)
    except OSError:
        return False
    return True
