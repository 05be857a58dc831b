"""Build step that pyproject.toml cannot declare: the `.pth` start-up hook for Open3D.

Everything else about the build is in pyproject.toml. The hook is one line in
`kitti_pu_open3d.pth`, placed at the root of the wheel (site-packages once installed), which calls
`_kitti_pu_open3d.install()`; that module says what it does and why.

Regular wheel (`pip install .`): the file is written into build_lib, which becomes the wheel's
root. Editable wheel (`pip install -e .`, PEP 660): setuptools' editable_wheel packs only its own
path finder from build_lib, but it points the `install` command's install_lib at the root of the
wheel it builds (where it also puts scripts and data), so the file is written there.
tests/test_packaging.py checks that both kinds of wheel carry it.
"""

from __future__ import annotations

from pathlib import Path

from setuptools import setup
from setuptools.command.build_py import build_py

PTH_NAME = "kitti_pu_open3d.pth"
# One line: site executes lines that start with "import". The try keeps an interpreter quiet if
# the module cannot be imported (e.g. an editable install whose source tree was moved).
PTH_LINE = 'import sys; exec("try:\\n import _kitti_pu_open3d\\n _kitti_pu_open3d.install()\\nexcept Exception:\\n pass")\n'


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
