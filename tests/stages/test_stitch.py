"""stages.stitch: generated points go back to the sensor frame, each object point keeps what its
owning patch generated from it, and input and ground points are kept or dropped as asked."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from stages import fill, ground, snap, stitch, tile, upsample
from stages.errors import StageError
from stages.frame import Frame
from stages.ring_snap import scan_rings

RATIO = 4
OFFSET = 0.02  # generated points lie within this (normalised) distance of their parent


class CopyUpsampler:
    """A stand-in model with the `cadpu.inference.Upsampler` interface and a known answer: each
    output point is its parent moved by a small offset. `uneven` draws the parent slots unevenly
    (as CAD-PU's curvature-adaptive expansion does) instead of exactly `ratio` per point."""

    def __init__(self, ratio: int = RATIO, uneven: bool = False, seed: int = 0) -> None:
        self.ratio = ratio
        self.uneven = uneven
        self.rng = np.random.default_rng(seed)

    def upsample_patches(self, patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        b, k, _ = patches.shape
        if self.uneven:
            parents = self.rng.integers(0, k, size=(b, k * self.ratio))
        else:
            parents = np.tile(np.repeat(np.arange(k), self.ratio), (b, 1))
        direction = self.rng.normal(size=(b, k * self.ratio, 3))
        direction /= np.linalg.norm(direction, axis=2, keepdims=True)
        points = np.take_along_axis(patches, parents[..., None], axis=1) + OFFSET * direction
        return points.astype(np.float32), parents.astype(np.int64)


def _frame(n: int = 3000, ground_every: int = 4, seed: int = 0) -> Frame:
    rng = np.random.default_rng(seed)
    xyz = rng.normal(size=(n, 3)) * [8.0, 8.0, 1.0] + rng.integers(0, 3, size=(n, 1)) * 15.0
    points = np.column_stack([xyz, rng.uniform(0, 1, n)]).astype(np.float32)
    ground = np.zeros(n, dtype=bool)
    if ground_every:
        ground[::ground_every] = True
    return Frame(points=points, dataset="bin", sequence="s", index=0, ground=ground)


def _upsampled(frame: Frame, model: CopyUpsampler | None = None, vertical_scale: float = 1.0) -> Frame:
    tiled = tile.run(frame, tile.Options(patch_size=256, overlap=1.0, seed=0, vertical_scale=vertical_scale))
    return upsample.run(tiled, upsampler=model or CopyUpsampler())


def test_each_object_point_gets_ratio_points_from_its_owner_patch() -> None:
    frame = _upsampled(_frame())
    objects = np.flatnonzero(~frame.ground)
    cloud = stitch.stitch(frame, keep_ground=False, keep_input=False)
    assert len(cloud) == RATIO * len(objects)
    assert cloud.generated.all() and not cloud.ground.any()
    assert np.array_equal(np.bincount(cloud.parent, minlength=len(frame.points))[objects],
                          np.full(len(objects), RATIO))


def test_stitch_points_assembles_the_same_cloud_from_arrays() -> None:
    # stitch took only a Frame, so a library user chaining stages on arrays rebuilt its order and
    # its reflectances from the source (a library user's trial)
    from cadpu.patches import keep_owned

    frame = _upsampled(_frame())
    xyz, source = keep_owned(frame.tiling, frame.upsampled, frame.parent_slots)
    for keep_ground in (True, False):
        made, expected = stitch.stitch_points(frame.points, frame.ground, xyz, source, keep_ground=keep_ground), \
            stitch.stitch(frame, keep_ground=keep_ground)
        for name in ("xyz", "reflectance", "generated", "ground", "parent"):
            assert np.array_equal(getattr(made, name), getattr(expected, name)), name
    alone = stitch.stitch_points(frame.points, frame.ground)  # nothing generated: the scan as it is
    assert len(alone) == len(frame.points) and not alone.generated.any()
    with pytest.raises(ValueError, match=r"stitch_points: source must index the \d+ object points"):
        stitch.stitch_points(frame.points, frame.ground, xyz, source + len(frame.points))
    with pytest.raises(ValueError, match=r"stitch_points: ground must be an \(3000,\) bool mask"):
        stitch.stitch_points(frame.points, frame.ground.astype(int), xyz, source)


def test_counts_with_inputs_and_ground() -> None:
    frame = _upsampled(_frame())
    m, g = int((~frame.ground).sum()), int(frame.ground.sum())
    assert len(stitch.stitch(frame, keep_ground=True, keep_input=False)) == RATIO * m + g
    assert len(stitch.stitch(frame, keep_ground=False, keep_input=True)) == (RATIO + 1) * m
    cloud = stitch.stitch(frame)
    assert len(cloud) == (RATIO + 1) * m + g
    assert int(cloud.generated.sum()) == RATIO * m and int(cloud.ground.sum()) == g


def test_generated_points_lie_near_their_parents_with_their_reflectance() -> None:
    frame = _upsampled(_frame())
    cloud = stitch.stitch(frame)
    assert cloud.xyz.dtype == np.float32 and cloud.reflectance.dtype == np.float32
    assert cloud.parent.dtype == np.int64 and cloud.generated.dtype == bool
    parents = frame.points[cloud.parent]
    assert np.array_equal(cloud.reflectance, parents[:, 3])
    distance = np.linalg.norm(cloud.xyz - parents[:, :3], axis=1)
    # Offset OFFSET in the unit sphere = OFFSET * scale metres in the owning patch.
    limit = OFFSET * frame.tiling.scale.max() * 1.001 + 1e-4
    assert distance[cloud.generated].max() <= limit
    assert distance[cloud.generated].min() > 0
    assert distance[~cloud.generated].max() == 0  # input and ground points unchanged
    assert not frame.ground[cloud.parent[cloud.generated]].any()  # nothing grows from the ground


def test_input_and_ground_points_are_kept_unchanged_and_point_to_themselves() -> None:
    frame = _upsampled(_frame())
    cloud = stitch.stitch(frame)
    kept = ~cloud.generated
    assert np.array_equal(np.sort(cloud.parent[kept]), np.arange(len(frame.points)))
    assert np.array_equal(cloud.xyz[kept], frame.points[cloud.parent[kept], :3])
    assert np.array_equal(cloud.ground, frame.ground[cloud.parent] & kept)


def test_uneven_parents_keep_exactly_what_each_owner_generated() -> None:
    frame = _upsampled(_frame(seed=1), CopyUpsampler(uneven=True, seed=3))
    tiling, parents = frame.tiling, frame.parent_slots
    objects = np.flatnonzero(~frame.ground)
    expected = np.zeros(len(frame.points), dtype=np.int64)
    for p in range(tiling.num_patches):  # the slow, obvious rule
        for slot in parents[p]:
            point = tiling.point_index[p, slot]
            if tiling.owner[point] == p:
                expected[objects[point]] += 1
    cloud = stitch.stitch(frame, keep_ground=False, keep_input=False)
    assert np.array_equal(np.bincount(cloud.parent, minlength=len(frame.points)), expected)


def test_frame_without_tiling_passes_through() -> None:
    frame = tile.run(_frame(n=400, ground_every=2), tile.Options(vertical_scale=1.0))  # 200 object points: no tiling
    frame = upsample.run(frame, upsampler=CopyUpsampler())
    assert frame.tiling is None and frame.upsampled is None
    cloud = stitch.stitch(frame)
    assert len(cloud) == 400 and not cloud.generated.any()
    assert np.array_equal(np.sort(cloud.parent), np.arange(400))
    assert np.array_equal(cloud.xyz, frame.points[cloud.parent, :3])
    assert len(stitch.stitch(frame, keep_ground=False)) == 200
    assert len(stitch.stitch(frame, keep_ground=False, keep_input=False)) == 200  # inputs always kept


@pytest.mark.parametrize("ground_every", [0, 1])
def test_frames_without_ground_or_only_ground(ground_every: int) -> None:
    frame = _upsampled(_frame(n=1000, ground_every=ground_every))
    cloud = stitch.stitch(frame)
    if ground_every == 0:
        assert len(cloud) == (RATIO + 1) * 1000 and not cloud.ground.any()
    else:
        assert frame.tiling is None and len(cloud) == 1000 and cloud.ground.all()


@pytest.mark.parametrize("keep_input", [True, False])
def test_patches_wider_than_the_limit_pass_through_unchanged(keep_input: bool) -> None:
    tiled = tile.run(_frame(), tile.Options(vertical_scale=1.0))
    scale = tiled.tiling.scale
    limit = float(np.median(scale))
    frame = upsample.run(tiled, upsample.Options(max_patch_radius=limit), upsampler=CopyUpsampler())
    wide = scale > limit
    assert wide.any() and (~wide).any()
    np.testing.assert_array_equal(frame.upsampled_patches, np.flatnonzero(~wide))
    assert len(frame.upsampled) == (~wide).sum()
    assert any("not upsampled" in note for note in frame.notes)
    cloud = stitch.stitch(frame, keep_ground=False, keep_input=keep_input)
    objects = np.flatnonzero(~frame.ground)
    in_wide = wide[frame.tiling.owner]
    per_parent = np.bincount(cloud.parent[cloud.generated], minlength=len(frame.points))[objects]
    assert np.all(per_parent[in_wide] == 0) and np.all(per_parent[~in_wide] == RATIO)
    # every object point is in the output once as input: those of wide patches even without keep_input
    kept = np.bincount(cloud.parent[~cloud.generated], minlength=len(frame.points))[objects]
    np.testing.assert_array_equal(kept, np.ones(len(objects)) if keep_input else in_wide)
    # generated points are near their parents, in the sensor frame
    gap = np.linalg.norm(cloud.xyz[cloud.generated] - frame.points[cloud.parent[cloud.generated], :3], axis=1)
    assert gap.max() < OFFSET * scale.max() * 1.01


def test_no_patch_narrow_enough_leaves_the_frame_as_it_was() -> None:
    tiled = tile.run(_frame(), tile.Options(vertical_scale=1.0))
    frame = upsample.run(tiled, upsample.Options(max_patch_radius=1e-6), upsampler=CopyUpsampler())
    cloud = stitch.stitch(frame, keep_ground=True, keep_input=False)
    assert not cloud.generated.any()
    np.testing.assert_array_equal(np.sort(cloud.parent), np.arange(len(frame.points)))


class LiftUpsampler(CopyUpsampler):
    """Each output point is its parent moved up by `lift` in the patch's unit sphere."""

    def __init__(self, lift: float) -> None:
        super().__init__()
        self.lift = lift

    def upsample_patches(self, patches: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        points, parents = super().upsample_patches(patches)
        points = np.take_along_axis(patches, parents[..., None], axis=1) + np.array([0.0, 0.0, self.lift])
        return points.astype(np.float32), parents


def test_vertical_scale_is_undone_and_stretches_vertical_offsets() -> None:
    scale = 0.2
    frame = _upsampled(_frame(), LiftUpsampler(0.0), vertical_scale=scale)
    cloud = stitch.stitch(frame, keep_ground=False, keep_input=False)
    # With no offset, every generated point is back exactly on its parent in the sensor frame.
    assert np.allclose(cloud.xyz, frame.points[cloud.parent, :3], atol=1e-4)
    lift = 0.05
    frame = _upsampled(_frame(), LiftUpsampler(lift), vertical_scale=scale)
    cloud = stitch.stitch(frame, keep_ground=False, keep_input=False)
    offset = cloud.xyz - frame.points[cloud.parent, :3]
    owner_radius = frame.tiling.scale[frame.tiling.owner[np.searchsorted(np.flatnonzero(~frame.ground),
                                                                        cloud.parent)]]
    assert np.allclose(offset[:, :2], 0.0, atol=1e-4)
    assert np.allclose(offset[:, 2], lift * owner_radius / scale, rtol=1e-3, atol=1e-4)


def _ring_frame(elevations_deg: tuple[float, ...] = (2.0, 0.4, -1.2, -2.8, -4.4, -6.0), per_ring: int = 900,
                distances: tuple[float, ...] | None = None) -> Frame:
    """A scan in KITTI order (ring by ring from the top, azimuth from just above 0 round to just
    below 0) of a cylinder 10 m round the sensor (or each ring at its own range, `distances`, m),
    with its lowest ring marked as ground."""
    rings = []
    for elevation, distance in zip(np.radians(elevations_deg), distances or [10.0] * len(elevations_deg)):
        azimuth = np.angle(np.exp(1j * np.linspace(0.001, 2 * np.pi - 0.001, per_ring)))
        horizontal = distance * np.cos(elevation)
        rings.append(np.column_stack([horizontal * np.cos(azimuth), horizontal * np.sin(azimuth),
                                      np.full(per_ring, distance * np.sin(elevation)), np.full(per_ring, 0.5)]))
    points = np.concatenate(rings).astype(np.float32)
    ground = np.zeros(len(points), dtype=bool)
    ground[-per_ring:] = True
    return Frame(points=points, dataset="bin", sequence="s", index=0, ground=ground, rings=scan_rings(points))


def _elevation_deg(xyz: np.ndarray) -> np.ndarray:
    xyz = np.asarray(xyz, dtype=np.float64)
    return np.degrees(np.arcsin(xyz[:, 2] / np.linalg.norm(xyz, axis=1)))


def test_run_snaps_generated_points_to_virtual_rings_and_drops_those_outside() -> None:
    frame = _upsampled(_ring_frame())
    plain = stitch.stitch(frame)
    result = _snapped(frame)
    cloud = result.cloud
    assert result.notes == frame.notes
    kept_input = ~cloud.generated
    assert np.array_equal(cloud.xyz[kept_input], plain.xyz[~plain.generated])  # input and ground untouched
    elevations = np.array([2.0, 0.4, -1.2, -2.8, -4.4, -6.0])
    virtual = (elevations[:-1, None] + np.diff(elevations)[:, None] * np.arange(1, RATIO) / RATIO).ravel()
    generated = _elevation_deg(cloud.xyz[cloud.generated])
    assert np.abs(generated[:, None] - virtual[None]).min(axis=1).max() < 1e-3
    # the generated points above the top ring have nowhere to go and are dropped
    above_top = int((_elevation_deg(plain.xyz[plain.generated]) > elevations[0]).sum())
    assert above_top > 0
    assert cloud.generated.sum() == plain.generated.sum() - above_top
    assert np.array_equal(cloud.reflectance, frame.points[cloud.parent, 3])


def _snapped(frame: Frame, range_tolerance: float | None = None, **stitch_options: bool) -> Frame:
    """The frame through the stitch and snap stages."""
    stitched = stitch.run(frame, stitch.Options(**stitch_options))
    return snap.run(stitched, snap.Options(range_tolerance=range_tolerance))


def test_snap_leaves_a_scan_without_ring_order_unsnapped_with_a_note() -> None:
    frame = _upsampled(_frame())
    assert frame.rings is None
    result = _snapped(frame)
    assert np.array_equal(result.cloud.xyz, stitch.stitch(frame).xyz)
    assert len(result.notes) == len(frame.notes) + 1 and "no laser rings" in result.notes[-1]


def test_stitch_run_adds_the_stitched_cloud_and_disabled_snap_and_fill_leave_it() -> None:
    frame = _upsampled(_ring_frame())
    result = stitch.run(frame, stitch.Options(keep_ground=False, keep_input=False))
    assert np.array_equal(result.cloud.xyz, stitch.stitch(frame, keep_ground=False, keep_input=False).xyz)
    assert snap.run(result, snap.Options(enabled=False)) is result
    assert fill.run(result, fill.Options(enabled=False)) is result
    # called out of order, before the stitch stage: an error naming the stage, not a silent no-op
    for stage in (snap, fill):
        with pytest.raises(StageError, match=rf"\[{stage.__name__.split('.')[-1]}\] .*run stages.stitch first"):
            stage.run(frame)


def test_snapping_with_a_range_tolerance_drops_generated_points_off_the_rings_surface() -> None:
    frame = _upsampled(_ring_frame())  # a cylinder: every return 10 m away, copies next to their parents
    plain = stitch.stitch(frame)
    generated = np.flatnonzero(plain.generated)
    pushed = generated[::2]  # every other copy pushed 1 m further along its ray: off the cylinder
    xyz = plain.xyz.copy()
    xyz[pushed] *= np.float32(1.1)
    cloud = dataclasses.replace(plain, xyz=xyz)
    kept_without = snap.snap_cloud(cloud, frame.points, frame.rings, frame.ratio, range_tolerance=None)
    kept_with = snap.snap_cloud(cloud, frame.points, frame.rings, frame.ratio, range_tolerance=0.05)
    pushed_kept = _generated_at(kept_without, 11.0)
    assert pushed_kept > 0 and _generated_at(kept_with, 11.0) == 0
    assert kept_without.generated.sum() - kept_with.generated.sum() == pushed_kept  # only those dropped
    assert kept_with.dropped - kept_without.dropped == pushed_kept  # and counted
    assert kept_without.dropped == plain.generated.sum() - kept_without.generated.sum()
    assert np.allclose(np.linalg.norm(kept_with.xyz[kept_with.generated], axis=1), 10.0, atol=0.05)
    assert np.array_equal(kept_with.xyz[~kept_with.generated], plain.xyz[~plain.generated])


def test_the_snap_stage_keeps_points_across_a_depth_edge_only_within_its_range_limit() -> None:
    # rings 0-2 on a wall 10 m away, rings 3-5 on a background 20 m away: the gap between rings 2
    # (-1.2 degrees) and 3 (-2.8) is a depth edge, whose half-gap points are copies of either side
    frame = _upsampled(_ring_frame(distances=(10.0, 10.0, 10.0, 20.0, 20.0, 20.0)))
    stitched = stitch.run(frame, stitch.Options())

    def across_edge(options: snap.Options) -> tuple[int, int]:
        cloud = snap.run(stitched, options).cloud
        xyz = cloud.xyz[cloud.generated]
        elevation = np.degrees(np.arcsin(xyz[:, 2] / np.linalg.norm(xyz, axis=1)))
        in_gap = (elevation < -1.25) & (elevation > -2.75)
        distance = np.linalg.norm(xyz[in_gap], axis=1)
        return int((np.abs(distance - 10.0) < 0.3).sum()), int((np.abs(distance - 20.0) < 0.3).sum())

    near, far = across_edge(snap.Options())
    assert near > 0 and far > 0
    assert across_edge(snap.Options(depth_edge_max_range=15.0)) == (near, 0)
    assert across_edge(snap.Options(depth_edge_max_range=25.0)) == (near, far)
    assert across_edge(snap.Options(depth_edges="drop")) == (0, 0)
    with pytest.raises(ValueError, match="depth_edge_max_range must be > 0"):  # as Options refuses it
        snap.snap_cloud(stitched.cloud, frame.points, frame.rings, frame.ratio, depth_edge_max_range=0.0)
    with pytest.raises(ValueError, match="a whole number >= 2, got 2.5"):  # ran without complaint before
        snap.snap_cloud(stitched.cloud, frame.points, frame.rings, 2.5)
    with pytest.raises(ValueError, match="snap_cloud: .* a whole number >= 2, got 1"):  # the kernels' own error (a review)
        snap.snap_cloud(stitched.cloud, frame.points, frame.rings, 1)
    # said as the range image's ("range image: ... points but rings has shape ...", a library user's trial)
    with pytest.raises(ValueError, match=r"^snap_cloud: range image: \d+ points but rings has shape"):
        snap.snap_cloud(stitched.cloud, frame.points, frame.rings[:-5], frame.ratio)
    # a scan and its cloud moved into a map frame: 99.7% of the network's points were dropped
    # without a word (a library user's trial)
    shift = np.array([3000.0, -2000.0, 0.0, 0.0], np.float32)
    moved = dataclasses.replace(stitched.cloud, xyz=stitched.cloud.xyz + shift[:3])
    with pytest.raises(ValueError, match=r"^snap_cloud: range image: \d+ of \d+ points lie beyond 200 m of the origin; "
                                         r".* must be in the sensor's frame"):
        snap.snap_cloud(moved, frame.points + shift, frame.rings, frame.ratio)


def test_the_snap_stage_notes_a_frame_whose_generated_points_almost_all_miss_its_rings() -> None:
    frame = _upsampled(_ring_frame())
    stitched = stitch.run(frame, stitch.Options())
    assert not any("generated points (" in note for note in snap.run(stitched, snap.Options()).notes)
    cloud = stitched.cloud
    xyz = cloud.xyz.copy()
    xyz[cloud.generated] *= np.float32(1.3)  # every copy 3 m off the cylinder: none fits
    result = snap.run(stitched.with_(cloud=dataclasses.replace(cloud, xyz=xyz)), snap.Options())
    assert result.cloud.generated.sum() == 0
    assert any("(100%) dropped, outside the scan's rings or off the ranges" in note for note in result.notes)
    # a scan turned into a camera's frame drew "is the scan stored in KITTI's ring order?" alone, and
    # a CLI option in a library call (a library user's trial)
    assert any("in the sensor's frame (x forward, z up)?" in note and "snap.enabled false in a library call" in note
               for note in result.notes)


def _generated_at(cloud: stitch.StitchedCloud, distance: float) -> int:
    """How many generated points of `cloud` lie within 0.3 m of `distance` metres from the sensor."""
    return int((np.abs(np.linalg.norm(cloud.xyz[cloud.generated], axis=1) - distance) < 0.3).sum())


def _ground_ring_frame() -> Frame:
    """`_ring_frame` with its three lowest rings on flat ground (z = -1.73 m) and marked ground."""
    frame = _ring_frame(elevations_deg=(2.0, 0.4, -1.2, -8.0, -9.5, -11.0))
    points = frame.points.copy()
    per_ring = len(points) // 6
    low = slice(3 * per_ring, None)
    elevation = np.arcsin(points[low, 2] / np.linalg.norm(points[low, :3], axis=1))
    points[low, :3] *= (-1.73 / np.sin(elevation) / np.linalg.norm(points[low, :3], axis=1))[:, None]
    ground = np.zeros(len(points), dtype=bool)
    ground[low] = True
    return frame.with_(points=points, ground=ground, rings=scan_rings(points))


def _filled(frame: Frame, **stitch_options: bool) -> Frame:
    """The frame through the stitch, snap and fill stages."""
    return fill.run(_snapped(frame, **stitch_options))


def test_run_fills_the_ground_between_rings_flagged_generated_and_ground() -> None:
    frame = _upsampled(_ground_ring_frame())
    result = _filled(frame)
    cloud, unfilled = result.cloud, _snapped(frame).cloud
    assert result.notes == frame.notes
    filled = cloud.generated & cloud.ground
    per_ring = len(frame.points) // 6
    assert filled.sum() == 2 * per_ring * (RATIO - 1)  # two gaps between the three ground rings, every column
    assert len(cloud) == len(unfilled) + filled.sum()
    np.testing.assert_allclose(cloud.xyz[filled, 2], -1.73, atol=1e-4)
    assert frame.ground[cloud.parent[filled]].all()
    # no ground fill without ground, and a scan without ring order gets the note instead
    assert not _filled(frame, keep_ground=False).cloud.ground.any()
    shuffled_points = frame.points[np.random.default_rng(0).permutation(len(frame.points))]
    shuffled = frame.with_(points=shuffled_points, rings=scan_rings(shuffled_points))
    assert shuffled.rings is None
    noted = fill.run(stitch.run(shuffled))
    assert not (noted.cloud.generated & noted.cloud.ground).any() and "ground not filled" in noted.notes[-1]


def test_fill_of_a_frame_without_patches_uses_the_ratio_the_upsample_stage_sets() -> None:
    frame = tile.run(_ground_ring_frame(), tile.Options(patch_size=4096))  # fewer object points than a patch
    with_ratio = fill.run(stitch.run(upsample.run(frame, upsampler=upsample.Options(ratio=2))))
    assert with_ratio.ratio == 2 and with_ratio.tiling is None
    assert (with_ratio.cloud.generated & with_ratio.cloud.ground).sum() == 2 * (len(frame.points) // 6)
    # without the upsample stage the number of virtual rings is unknown: said, not skipped silently
    with pytest.raises(StageError, match=r"\[fill\].*no upsampling ratio \(run stages.upsample first\)"):
        fill.run(stitch.run(frame))


def test_stages_called_out_of_order_say_which_stage_to_run_first() -> None:
    frame = _ring_frame()  # enough object points for patches
    with pytest.raises(StageError, match=r"\[upsample\] .*no patches \(run stages.tile first\)"):
        upsample.run(frame, upsampler=CopyUpsampler())
    with pytest.raises(StageError, match=r"\[stitch\] .*not upsampled \(run stages.upsample first\)"):
        stitch.run(tile.run(frame, tile.Options(patch_size=256, overlap=1.0)))
    # before the tile stage: the input alone came back as the cloud, without a word
    with pytest.raises(StageError, match=r"\[stitch\] .*no patches \(run stages.tile and stages.upsample first\)"):
        stitch.run(frame)
    few = tile.run(_ground_ring_frame(), tile.Options(patch_size=4096))  # too few object points: no patches
    assert tile.left_untiled(few) and upsample.run(few, upsampler=CopyUpsampler()).ratio == RATIO


def test_an_earlier_stage_run_again_clears_what_the_later_stages_made_from_its_old_result() -> None:
    upsampled = _upsampled(_ground_ring_frame())
    relabelled = ground.run(upsampled)  # new ground labels: the old patches no longer match them
    assert relabelled.tiling is None and relabelled.upsampled is None and relabelled.ratio is None
    # stitch mapped the old network output through the new labels, generated points metres from
    # their parents, without a word (a new-user trial)
    with pytest.raises(StageError, match=r"\[stitch\] .*no patches"):
        stitch.run(relabelled)
    retiled = tile.run(upsampled, tile.Options(patch_size=256, overlap=4 / 3))
    assert retiled.tiling is not None and retiled.upsampled is None
    with pytest.raises(StageError, match=r"\[stitch\] .*not upsampled"):
        stitch.run(retiled)
    stitched = stitch.run(upsampled)
    assert stitch.run(stitched).cloud is not None and upsample.run(stitched, upsampler=CopyUpsampler()).cloud is None
    untiled = tile.run(_ground_ring_frame(), tile.Options(patch_size=4096))  # too few object points: a note says so
    assert tile.left_untiled(untiled) and not tile.left_untiled(ground.run(untiled))  # the note went with the tiling


def test_snap_without_a_ratio_names_the_frame_and_the_stage_to_run() -> None:
    stitched = stitch.run(_upsampled(_ground_ring_frame()))
    # it said "[snap] cloud: needs the frame's upsampling ratio" (a new-user trial)
    with pytest.raises(StageError, match=r"\[snap\] bin/s/000000: the frame has no upsampling ratio \(run "
                                         r"stages.upsample first\)"):
        snap.run(stitched.with_(ratio=None))


def test_fill_run_twice_adds_nothing_the_second_time() -> None:
    once = _filled(_upsampled(_ground_ring_frame()))
    twice = fill.run(once)
    assert len(twice.cloud) == len(once.cloud)  # it appended every filled point again


def test_snap_after_fill_is_refused_not_run_on_the_filled_points() -> None:
    filled = _filled(_upsampled(_ground_ring_frame()))
    assert (filled.cloud.generated & filled.cloud.ground).any()
    # it moved and dropped the filled ground points without a word (a new-user trial)
    with pytest.raises(StageError, match=r"\[snap\] .*filled ground points \(stages.fill has run\): snap comes "
                                         "before fill"):
        snap.run(filled)


def test_per_point_fields_of_another_length_are_named_by_the_stage_that_reads_them() -> None:
    frame = _ground_ring_frame()
    with pytest.raises(StageError, match=r"\[tile\] .*frame.ground has shape \(100,\), not \(5400,\)"):
        tile.run(frame.with_(ground=frame.ground[:100]))  # an IndexError inside numpy before
    upsampled = _upsampled(frame)
    with pytest.raises(StageError, match=r"\[stitch\] .*frame.parent_slots has shape \(\d+, 10\)"):
        stitch.run(upsampled.with_(parent_slots=upsampled.parent_slots[:, :10]))  # a cloud was built from it
    stitched = stitch.run(upsampled)
    with pytest.raises(StageError, match=r"\[snap\] .*frame.rings has shape \(100,\)"):
        snap.run(stitched.with_(rings=stitched.rings[:100]), snap.Options())
    with pytest.raises(StageError, match=r"\[fill\] .*no ground labels \(run stages.ground first\)"):
        fill.run(stitched.with_(ground=None))  # a ValueError of the fill helper before


@pytest.mark.parametrize("dtype", [np.uint8, np.int64, np.float32])
def test_a_ground_mask_that_is_not_bool_is_refused_naming_the_field(dtype) -> None:
    frame = _ground_ring_frame()
    labels = frame.ground.astype(dtype)
    # a 0/1 mask went through `~`: -1/-2 indexed the last two points, and every generated point
    # sat at two positions, without an error (a library user's trial)
    with pytest.raises(StageError, match=rf"\[tile\] .*frame.ground holds {np.dtype(dtype).name}, not bool.*"
                                         r"labels.astype\(bool\)"):
        tile.run(frame.with_(ground=labels))
    upsampled = _upsampled(frame)
    with pytest.raises(StageError, match=r"\[stitch\] .*frame.ground holds"):
        stitch.run(upsampled.with_(ground=upsampled.ground.astype(dtype)))


def test_rings_that_are_not_whole_numbers_are_refused_naming_the_field() -> None:
    stitched = stitch.run(_upsampled(_ground_ring_frame()))
    with pytest.raises(StageError, match=r"\[snap\] .*frame.rings holds float64, not whole numbers"):
        snap.run(stitched.with_(rings=stitched.rings.astype(np.float64)), snap.Options())


def test_stitch_of_what_is_not_a_frame_is_refused_by_name() -> None:
    with pytest.raises(TypeError, match=r"stitch: takes a stages.frame.Frame, got NoneType"):
        stitch.stitch(None)  # an AttributeError inside before (a library user's trial)
