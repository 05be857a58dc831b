"""Import Open3D on machines that lack the system libusb.

Open3D's pip wheel links `libusb-1.0.so.0`, which bare machines do not have; the PyPI package
`libusb-package` ships that library. Loading it with RTLD_GLOBAL before `import open3d` lets the
dynamic linker resolve Open3D's dependency without any system package.
"""

from __future__ import annotations

import ctypes
from types import ModuleType


def import_open3d() -> ModuleType:
    """Return the `open3d` module, preloading libusb from `libusb-package` when needed."""
    try:
        import open3d

        return open3d
    except ImportError as first_error:
        if "libusb" not in str(first_error):
            raise
    import libusb_package

    library = libusb_package.get_library_path()
    if library is None:
        raise ImportError("open3d needs libusb-1.0 and libusb-package found no bundled copy")
    ctypes.CDLL(str(library), mode=ctypes.RTLD_GLOBAL)
    import open3d

    return open3d


o3d = import_open3d()
