"""The preview's crop finder on a made-up street (a car-sized box, a wall, a pole on a ground
plane) and the PNG it renders: written where asked, with a note where a crop kind is missing."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from matplotlib.figure import Figure

from pipeline import preview
from pipeline.preview import render_preview
from pipeline.preview_crops import find_crops


def _surface(rng: np.random.Generator, low: tuple[float, float, float], high: tuple[float, float, float],
             count: int) -> np.ndarray:
    return rng.uniform(low, high, size=(count, 3))


def _street(with_pole: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """(N, 3) points and (N,) ground flags: ground at z = -1.7, a 4.2 x 1.8 x 1.5 m car at x 8 m,
    a 12 m long, 4 m tall wall along x at y = -9 m, a 0.2 m thick, 4 m tall pole at (5, 6)."""
    rng = np.random.default_rng(3)
    parts = [
        _surface(rng, (-30, -20, -1.72), (30, 20, -1.68), 20_000),
        _surface(rng, (6.0, 2.0, -1.6), (10.2, 3.8, -0.1), 3_000),
        _surface(rng, (10.0, -9.1, -1.6), (22.0, -8.9, 2.3), 4_000),
    ]
    if with_pole:
        parts.append(_surface(rng, (4.9, 5.9, -1.6), (5.1, 6.1, 2.4), 800))
    xyz = np.concatenate(parts)
    ground = np.zeros(xyz.shape[0], bool)
    ground[:20_000] = True
    return xyz, ground


def test_crop_finder_finds_the_car_the_wall_and_the_pole() -> None:
    xyz, ground = _street()
    crops = find_crops(xyz, ground)
    expected = {"car": ((6.0, 2.0), (10.2, 3.8)), "wall": ((10.0, -9.1), (22.0, -8.9)), "pole": ((4.9, 5.9), (5.1, 6.1))}
    for kind, (low, high) in expected.items():
        crop = crops[kind]
        assert crop is not None, kind
        box_low, box_high = crop.bounds
        inside = crop.select(xyz[~ground])
        # The crop holds points of its structure: their centre lies inside the structure's footprint.
        centre = xyz[~ground][inside][:, :2].mean(axis=0) if kind != "wall" else None
        if centre is not None:
            assert np.all(centre >= np.array(low) - 0.6) and np.all(centre <= np.array(high) + 0.6), kind
        assert np.all(box_low[:2] <= np.array(high) + 1e-6) and np.all(box_high[:2] >= np.array(low) - 1e-6), kind
        assert box_high[2] - box_low[2] < 6.0 and np.all(box_high[:2] - box_low[:2] < 8.0), kind
    # The wall crop is a window at the wall's nearer end (x = 10 m), a few metres across.
    wall_low, wall_high = crops["wall"].bounds
    assert wall_low[0] < 10.0 < wall_high[0] and wall_high[0] < 16.0


def test_crop_finder_is_deterministic_and_reports_a_missing_pole() -> None:
    xyz, ground = _street(with_pole=False)
    first, second = find_crops(xyz, ground), find_crops(xyz[::-1], ground[::-1])
    assert first["pole"] is None and first["car"] is not None and first["wall"] is not None
    assert first == find_crops(xyz, ground)
    assert np.allclose(first["car"].bounds[0], second["car"].bounds[0], atol=1e-6)


def test_preview_png_is_written_and_notes_a_missing_crop(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    xyz, ground = _street(with_pole=False)
    rng = np.random.default_rng(4)
    added = xyz[~ground][::3] + rng.normal(0, 0.02, size=(xyz[~ground][::3].shape[0], 3))
    after = np.concatenate([xyz, added])
    generated = np.r_[np.zeros(xyz.shape[0], bool), np.ones(added.shape[0], bool)]
    texts: list[str] = []
    savefig = Figure.savefig

    def record(figure: Figure, *args, **kwargs):
        texts.extend(text.get_text() for axis in figure.axes for text in axis.texts)
        return savefig(figure, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", record)
    png = render_preview(xyz, after, tmp_path / "preview" / "frame.png", title="frame",
                         after_generated=generated, after_ground=np.r_[ground, np.zeros(added.shape[0], bool)])
    assert png == tmp_path / "preview" / "frame.png"
    assert png.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert any("no pole found" in text for text in texts)
    assert not any("no car found" in text or "no wall found" in text for text in texts)
    assert not hasattr(preview, "MAX_PLOTTED")


def test_a_street_scanned_along_its_length_gets_bird_s_eye_panels_the_figure_s_width(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    # side by side, the demo's street (150 m long, 19 m wide: the README's first output) filled a
    # sixth of each nearly square panel, the rest white (an earlier note)
    rng = np.random.default_rng(5)
    street = np.concatenate([rng.uniform((-30, -8, -1.72), (120, 11, -1.68), (20_000, 3)), _street()[0][20_000:]])
    scan = rng.uniform((-80, -80, -1.72), (80, 80, -1.68), (20_000, 3))  # a scan of open ground, all round
    spans: list[list[tuple[float, float, float, float]]] = []
    savefig = Figure.savefig

    def record(figure: Figure, *args, **kwargs):
        spans.append([tuple(axis.get_position().bounds) for axis in figure.axes[:2]])  # before, after
        return savefig(figure, *args, **kwargs)

    monkeypatch.setattr(Figure, "savefig", record)
    for cloud in (street, scan):
        render_preview(cloud, cloud, tmp_path / "frame.png")
    (before, after), (scan_before, scan_after) = spans
    assert before[2] > 0.9 and after[2] > 0.9 and after[1] < before[1]  # each the full width, one above the other
    assert scan_before[2] < 0.5 and abs(scan_before[1] - scan_after[1]) < 1e-6  # side by side, as before
    stacked, height = preview.bird_layout(street[:, :2])
    assert stacked and preview.BIRD_MIN_HEIGHT <= height < 3


def test_a_scan_of_the_kitti_mirror_previews_into_the_outputs_preview_folder(tmp_path: Path) -> None:
    from stages import write
    from stages.frame import Frame, StitchedCloud

    scan = np.random.default_rng(0).uniform(0, 10, (300, 4)).astype(np.float32)
    out = tmp_path / "out"
    paths = {}
    for sequence in ("05", "10"):
        source = tmp_path / "odometry" / "sequences" / sequence / "velodyne" / "000012.bin"
        source.parent.mkdir(parents=True)
        scan.tofile(source)
        frame = Frame(points=scan, dataset="odometry", sequence=sequence, index=12, source=str(source))
        cloud = StitchedCloud(xyz=scan[:, :3], reflectance=scan[:, 3], generated=np.zeros(300, bool),
                              ground=np.zeros(300, bool), parent=np.arange(300))
        paths[sequence] = write.write_frame(cloud, frame, out, {}, formats=("parquet", "kitti"))["kitti"]
    # ./000012.png for both, each overwriting the other (a new-user trial)
    assert preview.default_png_path(paths["05"]) == out / "preview" / "odometry" / "05" / "000012.png"
    assert preview.default_png_path(paths["10"]) == out / "preview" / "odometry" / "10" / "000012.png"
    assert preview.default_png_path(tmp_path / "odometry" / "sequences" / "05" / "velodyne" / "000012.bin") == \
        Path("000012.png")  # the input scan is no frame of OUT
