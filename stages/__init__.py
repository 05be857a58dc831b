"""The stages of a frame's journey (docs/ARCHITECTURE.md); importing them preloads libusb for Open3D."""

import cadpu  # noqa: F401  (makes a plain `import open3d` work: cadpu/_libusb.py)
