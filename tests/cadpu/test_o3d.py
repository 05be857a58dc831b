"""cadpu.o3d: Open3D imported after the libusb preload; its absence named with the extra."""

from __future__ import annotations

import sys

import pytest

from cadpu.o3d import import_open3d, o3d


def test_open3d_imports_and_reads_what_it_is_given() -> None:
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector([[0.0, 0.0, 0.0], [1.0, 2.0, 3.0]]))
    assert len(cloud.points) == 2


def test_missing_open3d_names_the_extra(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setitem(sys.modules, "open3d", None)  # how Python marks a module that cannot be imported
    with pytest.raises(ImportError, match=r'open3d extra: pip install "kitti-pu\[open3d\]"'):
        import_open3d()
