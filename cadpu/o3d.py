"""Import Open3D on machines that lack the system libusb.

Open3D's pip wheel links `libusb-1.0.so.0`, which bare machines do not have; the PyPI package
`libusb-package` (a dependency of kitti-pu) ships that library. Loading it with RTLD_GLOBAL before
`import open3d` lets the dynamic linker resolve Open3D's dependency without any system package.

`preload_libusb` does that and nothing else; importing any kitti-pu package (`cadpu`, `stages`,
`pipeline`) calls it, so a plain `import open3d` works in a process that has imported one of
them first.
"""

from __future__ import annotations

from types import ModuleType

from ._libusb import preload_libusb


def import_open3d() -> ModuleType:
    """Return the `open3d` module, preloading libusb from `libusb-package` when needed."""
    if not preload_libusb():
        raise ImportError("open3d needs libusb-1.0: neither the system nor libusb-package provides it")
    import open3d

    return open3d


o3d = import_open3d()
