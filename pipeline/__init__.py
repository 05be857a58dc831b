"""The pipeline: configuration, the chain, the Dask runner and the CLI; importing it preloads libusb for Open3D."""

import cadpu  # noqa: F401  (makes a plain `import open3d` work: cadpu/_libusb.py)
