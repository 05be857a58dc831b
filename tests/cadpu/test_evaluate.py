"""Tests of the object-level evaluation's held-out sets (`cadpu.evaluate`)."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from cadpu.evaluate import held_out_cases, main, poisson_surface
from cadpu.synthetic.shapes import FAMILIES


def test_held_out_meshes_from_an_offset_are_those_of_the_full_list() -> None:
    full = held_out_cases(5)
    later = held_out_cases(2, first=3)
    assert [c.name for c in later] == [c.name for c in full[3:]]
    for a, b in zip(later, full[3:]):
        assert np.array_equal(a.inputs, b.inputs)
        assert np.array_equal(a.mesh.vertices, b.mesh.vertices)
    # the shape families keep cycling with the absolute index
    assert [c.name.rsplit("-", 1)[0] for c in later] == [list(FAMILIES)[i % len(FAMILIES)] for i in (3, 4)]


def test_the_poisson_reconstruction_is_the_same_on_every_call() -> None:
    """Open3D's multi-threaded reconstruction differed from call to call (and crashes now and then);
    the evaluation's reconstruction runs on one thread and is deterministic."""
    pytest.importorskip("open3d")
    rng = np.random.default_rng(0)
    points = rng.normal(size=(8192, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    points[:, 2] *= 0.6
    first = poisson_surface(points)
    for _ in range(3):
        again = poisson_surface(points)
        assert np.array_equal(again.vertices, first.vertices)
        assert np.array_equal(again.triangles, first.triangles)


@pytest.mark.parametrize("args, message", [
    (["--pugan", "/nonexistent/pugan"], "no PU-GAN test meshes there"),
    (["--meshes", "0"], "--meshes must be at least 1"),
    (["--weights", "/nonexistent/w.pt"], "w.pt"),
    (["--meshes", "1", "--csv", "/"], "--csv /: not a file that can be written"),  # found after the evaluation
    (["--meshes", "1", "--csv", "MISSING/out.csv"], "--csv MISSING/out.csv: not a file that can be written"),
    (["--meshes", "1", "--oversample", "9"], "cadpu.evaluate: Upsampler: oversample must be a whole number from 1 to 8"),
    (["--meshes", "1", "--offset-scale", "0"], "cadpu.evaluate: Upsampler: offset_scale must be a number above 0"),
])
def test_bad_arguments_exit_2_with_one_line(args: list[str], message: str, tmp_path: Path,
                                            capsys: pytest.CaptureFixture[str]) -> None:
    # a folder surely missing: /nonexistent is a real home folder of uid 65534 on some machines
    missing = str(tmp_path / "missing")
    args, message = [arg.replace("MISSING", missing) for arg in args], message.replace("MISSING", missing)
    with pytest.raises(SystemExit) as stop:
        main(args)
    said = capsys.readouterr().err
    assert stop.value.code == 2 and message in said
    assert "the protocol upsamples" not in said  # said only of a ratio the weights cannot make (a trial)


def test_without_open3d_it_names_the_extra_before_any_mesh() -> None:
    import subprocess
    import sys

    script = ("import sys; sys.modules['open3d'] = None  # as where the extra is not installed\n"
              "from cadpu.evaluate import main; main(['--meshes', '1'])")
    result = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300)
    # it evaluated a mesh, then ended in a traceback with exit 1 (a new-user trial)
    assert result.returncode == 2, result.stderr[-2000:]
    assert result.stderr.strip() == ('cadpu.evaluate: Open3D is not installed; it is the optional open3d extra: '
                                     'pip install "kitti-pu[open3d]"')
    assert result.stdout == ""


def test_weights_of_another_trained_ratio_are_refused_not_scored_at_their_own(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    # a 16x file was scored with 32,768 points beside the baseline's 8,192, and "won" on CD
    import torch

    from cadpu import weights
    from cadpu.network import Generator

    torch.manual_seed(0)
    sixteen = tmp_path / "r16.pt"
    weights.save(Generator(ratio=16), sixteen)
    with pytest.raises(SystemExit) as stop:
        main(["--meshes", "1", "--weights", str(sixteen)])
    assert stop.value.code == 2
    assert f"cadpu.evaluate: {sixteen}: ratio 4 is not the trained ratio 16 or a power of it" in capsys.readouterr().err


def test_each_network_runs_with_its_own_oversampling_and_offset_scale_unless_one_is_given() -> None:
    from cadpu.evaluate import methods, table

    own = list(methods(None, None))
    assert own[:2] == ["CAD-PU (shipped, alpha 0.5, oversample 2, offset scale 1.4)", "CAD-PU alpha 1.0 (uniform)"]
    assert list(methods(None, None, oversample=1))[:2] == ["CAD-PU (shipped, alpha 0.5, offset scale 1.4)",
                                                           "CAD-PU alpha 1.0 (uniform)"]
    assert list(methods(None, None, oversample=1, offset_scale=1))[:2] == ["CAD-PU (shipped, alpha 0.5)",
                                                                           "CAD-PU alpha 1.0 (uniform)"]
    assert list(methods(None, None, offset_scale=1.2))[1] == "CAD-PU alpha 1.0 (uniform, offset scale 1.2)"
    rows = [{"mesh": "m", "method": name, **{m: 0.001 for m in ("CD", "HD", "P2F", "CD_rec", "HD_rec")}} for name in own]
    lines = table(rows, "g").splitlines()
    assert len({line.index("1.000") for line in lines[2:]}) == 1  # the columns line up under long names


def _write_pugan_case(folder: Path, name: str, points: int = 2048, scale: float = 1.0,
                      offset: tuple[float, float, float] = (0.0, 0.0, 0.0), xyz: bool = True) -> None:
    """NAME.off (a held-out mesh, moved and scaled) and NAME.xyz (points on it), as PU-GAN ships them."""
    case = held_out_cases(1)[0]
    vertices = case.mesh.vertices * scale + np.array(offset)
    lines = ["OFF", f"{len(vertices)} {len(case.mesh.triangles)} 0"]
    lines += [" ".join(f"{x:.17g}" for x in v) for v in vertices] + [f"3 {a} {b} {c}" for a, b, c in case.mesh.triangles]
    (folder / f"{name}.off").write_text("\n".join(lines) + "\n")
    if xyz:
        np.savetxt(folder / f"{name}.xyz", case.inputs[:points] * scale + np.array(offset))


def test_a_pugan_mesh_outside_the_unit_sphere_is_moved_into_it_with_its_input(tmp_path: Path) -> None:
    # the distances of a mesh in millimetres far from the origin were printed as "x 1e-3 (unit
    # sphere)", 100 times too large (a trial)
    from cadpu.evaluate import pugan_cases

    _write_pugan_case(tmp_path, "given")
    _write_pugan_case(tmp_path, "moved", scale=100.0, offset=(500.0, 0.0, 0.0))
    given, moved = pugan_cases(tmp_path)
    assert given.name == "given" and np.array_equal(given.mesh.vertices, held_out_cases(1)[0].mesh.vertices)
    assert np.allclose(moved.mesh.vertices, given.mesh.vertices, atol=1e-9)
    assert np.allclose(moved.inputs, given.inputs, atol=1e-9)


@pytest.mark.parametrize("points, xyz, message", [
    (2048, False, "missing.xyz: cannot be read as x y z rows"),
    (2001, True, "missing.xyz: 2001 input points; the protocol takes 2048 (8 clusters of 256)"),
])
def test_a_pugan_folder_without_a_whole_input_is_refused_naming_the_file(
        tmp_path: Path, points: int, xyz: bool, message: str, capsys: pytest.CaptureFixture[str]) -> None:
    # a numpy traceback, or "need a power-of-two number of parts dividing 2001", after the held-out
    # meshes' evaluation (a trial)
    _write_pugan_case(tmp_path, "missing", points=points, xyz=xyz)
    with pytest.raises(SystemExit) as stop:
        main(["--meshes", "0", "--pugan", str(tmp_path)])
    assert stop.value.code == 2 and message in capsys.readouterr().err


def test_the_table_counts_its_meshes_in_words() -> None:
    from cadpu.evaluate import table

    row = {"mesh": "a", "method": "m", "points": 8, "CD": 1.0, "HD": 2.0, "P2F": 0.5, "CD_rec": 1.0, "HD_rec": 2.0}
    assert table([row], "held-out").splitlines()[0].startswith("held-out: mean over 1 mesh, ")  # "1 meshes" before
    assert table([row, {**row, "mesh": "b"}], "held-out").splitlines()[0].startswith("held-out: mean over 2 meshes, ")
