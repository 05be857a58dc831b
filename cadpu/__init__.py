"""CAD-PU: the curvature-adaptive point set upsampling network, its training and evaluation.

Importing the package makes Open3D importable on machines without the system libusb
(`cadpu._libusb.preload_libusb`): after `import cadpu`, a plain `import open3d` works.
"""

from ._libusb import preload_libusb as _preload_libusb

_preload_libusb()
