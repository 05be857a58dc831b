"""Import Open3D, an optional extra of kitti-pu, on machines that lack the system libusb.

Open3D is the `open3d` extra (`pip install "kitti-pu[open3d]"`, part of the `test` extra): the
simulated LiDAR casts its rays with it (`cadpu.synthetic.lidar`: the demo, training on simulated
scans), `cadpu.metrics.point_to_surface` and `cadpu.evaluate` measure and reconstruct surfaces with
it, the "ransac" ground method fits its plane with it, and the tests read the PLY output back with
it. Without it, `import_open3d` raises an ImportError naming the extra. Its pip wheel links
`libusb-1.0.so.0`, which bare machines do not have; the PyPI package `libusb-package` (in the
same extra) ships that library. Loading it with RTLD_GLOBAL before `import open3d` lets the
dynamic linker resolve Open3D's dependency without any system package.

`preload_libusb` does that and nothing else. A kitti-pu install runs it before a plain
`import open3d` (the start-up hook that setup.py installs), and importing any kitti-pu package
(`cadpu`, `stages`, `pipeline`) runs it too.
"""

from __future__ import annotations

from types import ModuleType

from ._libusb import preload_libusb

#: How to install what this module needs.
OPEN3D_EXTRA = 'pip install "kitti-pu[open3d]"'


def import_open3d() -> ModuleType:
    """Return the `open3d` module, preloading libusb from `libusb-package` when needed.

    Raises:
        ImportError: Open3D or libusb missing, naming the extra that installs them.
    """
    libusb = preload_libusb()
    try:
        import open3d
    except ImportError as error:
        if getattr(error, "name", None) == "open3d":
            raise ImportError(f"Open3D is not installed; it is the optional open3d extra: {OPEN3D_EXTRA}",
                              name="open3d") from None
        if not libusb:
            raise ImportError("Open3D needs libusb-1.0: neither the system nor libusb-package provides "
                              f"it ({OPEN3D_EXTRA} installs libusb-package)") from error
        raise
    return open3d


o3d = import_open3d()
