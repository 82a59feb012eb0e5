"""The synthetic street world: determinism, exact stereo geometry, route revisits, aliasing, drift."""

from __future__ import annotations

import math

import cv2
import numpy as np
import pytest

from lcv_replay.errors import ConfigError
from lcv_replay.records import Pose2D
from recorders.synthetic import DriftConfig, simulate_odometry
from recorders.synthetic_world import ROUTE_CYCLE, SyntheticWorld, WorldConfig, make_route, t_body_camera

# Coarser textures than the default (same layout code): 4x fewer texels to draw in the tests.
SMALL = WorldConfig(texture_px_per_m=16.0, ground_px_per_m=12.0)
W, H = 320, 240


@pytest.fixture(scope="module")
def world() -> SyntheticWorld:
    return SyntheticWorld.from_seed(3, SMALL)


@pytest.fixture(scope="module")
def route() -> np.ndarray:
    return make_route(SyntheticWorld.from_seed(0), 1500)


def facing_pose(world: SyntheticWorld, face_id: int, distance_m: float, along_m: float = 0.0) -> Pose2D:
    """A body pose ``distance_m`` in front of a street face's building line, looking at it."""
    face = world.street_faces[face_id]
    x, y = face.centre_xy
    if face.facing == "south":
        return Pose2D(x + along_m, y - distance_m, math.pi / 2)
    return Pose2D(x - along_m, y + distance_m, -math.pi / 2)


def test_same_seed_gives_identical_world_and_images(world):
    again = SyntheticWorld.from_seed(3, SMALL)
    for name in ("a_xy", "b_xy", "height_m", "texture_id", "gain"):
        np.testing.assert_array_equal(getattr(world.walls, name), getattr(again.walls, name))
    pose = Pose2D(12.0, -2.5, 0.1)
    left, right = world.render_stereo(pose, width_px=W, height_px=H)
    left2, right2 = again.render_stereo(pose, width_px=W, height_px=H)
    assert left.shape == (H, W, 3) and left.dtype == np.uint8
    np.testing.assert_array_equal(left, left2)
    np.testing.assert_array_equal(right, right2)
    other = SyntheticWorld.from_seed(4, SMALL)
    assert not np.array_equal(other.walls.texture_id[:50], world.walls.texture_id[:50])
    assert np.abs(other.render_stereo(pose, width_px=W, height_px=H)[0].astype(int) - left).mean() > 5


def test_image_is_a_street_scene(world):
    """Sky on top, ground at the bottom, textured walls in between (not noise, not blank)."""
    image, depth = world.render_view(Pose2D(30.0, -2.5, 0.0), width_px=W, height_px=H, with_depth=True)
    grey = cv2.cvtColor(image, cv2.COLOR_RGB2GRAY)
    assert np.isinf(depth).any() and np.isinf(depth[: H // 2]).mean() > np.isinf(depth[H // 2 :]).mean()
    sky = image[np.isinf(depth)]
    assert (sky[:, 2].astype(int) > sky[:, 0].astype(int)).mean() > 0.8  # blue-ish
    assert np.isfinite(depth[-1]).all()  # the bottom row sees the ground
    corners = cv2.goodFeaturesToTrack(grey, 500, 0.01, 5)
    assert corners is not None and len(corners) > 150  # enough texture for VO
    # Neighbouring pixels are strongly correlated (a rendered scene, not noise).
    g = grey.astype(float)
    assert np.corrcoef(g[:, :-1].ravel(), g[:, 1:].ravel())[0, 1] > 0.8


@pytest.mark.parametrize("pose", [Pose2D(30.0, -2.5, 0.0), Pose2D(57.0, 3.0, 2.0), Pose2D(2.5, 25.0, math.pi / 2)])
def test_right_image_is_left_image_shifted_by_disparity(world, pose):
    """Warping the right image by d = fx * b / Z (Z from the left depth) reproduces the left image."""
    calib = world.calibration(W, H)
    left, depth = world.render_view(pose, "left", width_px=W, height_px=H, with_depth=True)
    right, depth_r = world.render_view(pose, "right", width_px=W, height_px=H, with_depth=True)
    disparity = np.where(np.isfinite(depth), calib.fx_px * calib.baseline_m / depth, 0.0).astype(np.float32)
    map_x = (np.arange(W, dtype=np.float32)[None, :] - disparity).astype(np.float32)
    map_y = np.repeat(np.arange(H, dtype=np.float32)[:, None], W, axis=1)
    warped = cv2.remap(right, map_x, map_y, cv2.INTER_LINEAR)
    depth_at_match = cv2.remap(np.where(np.isfinite(depth_r), depth_r, 1e6).astype(np.float32), map_x, map_y, cv2.INTER_NEAREST)
    visible = np.isfinite(depth) & (map_x >= 1) & (depth < 150) & (np.abs(depth_at_match - depth) < 0.02 * depth)
    assert visible.mean() > 0.5
    error = np.abs(warped.astype(int) - left.astype(int)).mean(axis=2)[visible]
    assert np.median(error) <= 1.0 and np.percentile(error, 90) < 6.0


def test_block_matching_disparity_equals_fx_b_over_z():
    """Disparity measured by block matching at texture corners equals fx * b / Z within a pixel."""
    world = SyntheticWorld.from_seed(5, WorldConfig(texture_px_per_m=16.0, ground_px_per_m=12.0, lamp_spacing_m=0.0))
    calib = world.calibration(W, H)
    face = next(f for f in world.street_faces if f.facing == "south" and f.block == (0, 0))
    pose = facing_pose(world, face.face_id, distance_m=8.0)
    left, depth = world.render_view(pose, "left", width_px=W, height_px=H, with_depth=True)
    right, _ = world.render_view(pose, "right", width_px=W, height_px=H)
    # Looking straight at the building line from 8 m: the facade's depth is exactly 8 m.
    wall = np.isfinite(depth[: int(calib.cy_px)])
    assert np.isclose(np.median(depth[: int(calib.cy_px)][wall]), 8.0, atol=1e-4)
    gl, gr = (cv2.cvtColor(x, cv2.COLOR_RGB2GRAY).astype(np.float32) for x in (left, right))
    corners = cv2.goodFeaturesToTrack(gl.astype(np.uint8), 200, 0.02, 6).reshape(-1, 2)
    half, max_d = 5, 60
    errors = []
    for u, v in np.rint(corners).astype(int):
        z = depth[v, u]
        if not (half + max_d <= u < W - half and half <= v < H - half and np.isfinite(z)):
            continue
        patch = gl[v - half : v + half + 1, u - half : u + half + 1]
        ssd = np.array([((gr[v - half : v + half + 1, u - d - half : u - d + half + 1] - patch) ** 2).sum() for d in range(max_d)])
        d = int(np.argmin(ssd))
        if 0 < d < max_d - 1:  # sub-pixel parabola
            d = d + 0.5 * (ssd[d - 1] - ssd[d + 1]) / (ssd[d - 1] - 2 * ssd[d] + ssd[d + 1])
        errors.append(abs(d - calib.fx_px * calib.baseline_m / z))
    assert len(errors) >= 30
    assert np.mean(np.array(errors) < 1.0) > 0.9 and np.median(errors) < 0.3


def test_calibration_and_camera_mount():
    world = SyntheticWorld.from_seed(0)
    calib = world.calibration(640, 480)
    assert (calib.fx_px, calib.fy_px, calib.cx_px, calib.cy_px, calib.baseline_m) == (384.0, 384.0, 319.5, 239.5, 0.5)
    assert world.calibration(320, 240).fx_px == 192.0
    T = t_body_camera(world.config)
    np.testing.assert_allclose(T[:3, :3] @ [0, 0, 1], [1, 0, 0])  # optical z = body x (forward)
    np.testing.assert_allclose(T[:3, :3] @ [1, 0, 0], [0, -1, 0])  # optical x = body -y (right)
    np.testing.assert_allclose(T[:3, 3], [0, 0, 1.6])
    left, right = world.camera_positions(Pose2D(1.0, 2.0, math.pi / 2))
    np.testing.assert_allclose(left, (1.0, 2.0))
    np.testing.assert_allclose(right, (1.5, 2.0), atol=1e-12)  # heading north, the right camera is east
    with pytest.raises(ConfigError):
        world.calibration(8, 8)
    with pytest.raises(ConfigError):
        world.render_view(Pose2D(float("nan"), 0.0, 0.0), width_px=32, height_px=24)


def test_route_revisits_places_three_times_once_in_the_opposite_direction(route):
    steps = np.hypot(*np.diff(route[:, :2], axis=0).T)
    assert steps.max() <= 1.0 + 1e-6 and steps.min() > 0.3 and 0.7 < steps.mean() <= 1.0
    yaw_rate = np.abs((np.diff(route[:, 2]) + np.pi) % (2 * np.pi) - np.pi)
    assert np.degrees(yaw_rate.max()) < 6.0  # smooth turns
    n = len(route)
    dist = np.hypot(route[:, None, 0] - route[None, :, 0], route[:, None, 1] - route[None, :, 1])
    query, match = np.nonzero((dist < 10.0) & (np.arange(n)[:, None] - np.arange(n)[None, :] > 200))
    queries = np.unique(query)
    events = np.split(queries, np.flatnonzero(np.diff(queries) > 1) + 1)
    assert len(events) >= 3
    heading_gap = np.abs((route[query, 2] - route[match, 2] + np.pi) % (2 * np.pi) - np.pi)
    assert np.degrees(heading_gap.max()) > 170  # a revisit in the opposite direction
    assert (np.degrees(heading_gap) < 10).sum() > 100  # and many in the same direction


def test_short_route_is_a_prefix_and_still_revisits():
    world = SyntheticWorld.from_seed(0)
    long = make_route(world, 1500)
    short = make_route(world, 400)
    np.testing.assert_allclose(short, long[:400], atol=1e-9)
    d = np.hypot(*(short[330:, None, :2] - short[None, :100, :2]).transpose(2, 0, 1))
    assert d.min() < 3.0  # the first block loop closes within 400 frames
    assert len(ROUTE_CYCLE) == 26
    with pytest.raises(ConfigError):
        make_route(world, 0)


def test_aliasing_cloned_street_faces_look_the_same(world):
    """Distinct places share facade textures, and cloned street faces render (nearly) identically."""
    walls = world.walls
    street = np.flatnonzero(walls.street_facing)
    centres = walls.centre_xy[street]
    shared_far = 0
    for tex in np.unique(walls.texture_id[street]):
        c = centres[walls.texture_id[street] == tex]
        if len(c) > 1 and np.hypot(*(c[:, None] - c[None]).transpose(2, 0, 1)).max() > 100.0:
            shared_far += 1
    assert shared_far >= 10
    clones = [f for f in world.street_faces if f.cloned_from is not None]
    assert len(clones) == world.config.cloned_street_faces
    clone = clones[0]
    source = world.street_faces[clone.cloned_from]
    assert np.hypot(*np.subtract(clone.centre_xy, source.centre_xy)) > 50.0  # another block
    views = {}
    for face in (clone, source):
        image, depth = world.render_view(facing_pose(world, face.face_id, 2.3), width_px=W, height_px=H, with_depth=True)
        views[face.face_id] = (image.astype(int), np.isclose(depth, 2.3, atol=1e-3))
    same = views[clone.face_id][1] & views[source.face_id][1]
    assert same.mean() > 0.3
    assert np.abs(views[clone.face_id][0] - views[source.face_id][0])[same].mean() < 3.0
    # A face that is not a copy looks different from the same viewpoint.
    other = next(f for f in world.street_faces if f.facing == source.facing and f.cloned_from is None and f.face_id != source.face_id and f.block != source.block)
    image, depth = world.render_view(facing_pose(world, other.face_id, 2.3), width_px=W, height_px=H, with_depth=True)
    both = np.isclose(depth, 2.3, atol=1e-3) & views[source.face_id][1]
    assert np.abs(image.astype(int) - views[source.face_id][0])[both].mean() > 10.0


def test_simulated_odometry_drift_grows_with_distance(route):
    distance = np.concatenate([[0.0], np.cumsum(np.hypot(*np.diff(route[:, :2], axis=0).T))])
    marks = [np.searchsorted(distance, d) for d in (100.0, 400.0, 1000.0)]
    errors = []
    for seed in range(12):
        odom = simulate_odometry(route, DriftConfig(), seed)
        # Odometry lives in the odom frame (the first body pose): express the truth there too.
        c, s = math.cos(route[0, 2]), math.sin(route[0, 2])
        rel = route[:, :2] - route[0, :2]
        truth = np.stack([c * rel[:, 0] + s * rel[:, 1], -s * rel[:, 0] + c * rel[:, 1]], axis=1)
        errors.append([np.hypot(*(odom[k, :2] - truth[k])) for k in marks])
    median = np.median(errors, axis=0)
    assert median[0] < median[1] < median[2]
    assert 3.0 < median[2] < 25.0  # "several to ~20 m after ~1 km"
    np.testing.assert_array_equal(simulate_odometry(route, DriftConfig(), 7), simulate_odometry(route, DriftConfig(), 7))
    assert not np.allclose(simulate_odometry(route, DriftConfig(), 7), simulate_odometry(route, DriftConfig(), 8))


def test_zero_drift_reproduces_the_true_motion(route):
    odom = simulate_odometry(route[:300], DriftConfig(0.0, 0.0, 0.0, 0.0), seed=1)
    np.testing.assert_allclose(odom[0], 0.0)
    start = Pose2D(*route[0])
    for k in (50, 299):
        expected = start.between(Pose2D(*route[k]))
        np.testing.assert_allclose(odom[k], expected.as_array(), atol=1e-9)
    assert DriftConfig(0.0, 0.0, 0.0, 0.0).step_information() is None
    np.testing.assert_allclose(np.diag(DriftConfig().step_information(1.0))[:2], 1.0 / 0.01**2)


@pytest.mark.parametrize(
    "kwargs",
    [dict(translation_noise_pct=-1.0), dict(yaw_noise_deg_per_m=float("nan")), dict(scale_bias_pct=50.0)],
)
def test_bad_drift_config_is_refused(kwargs):
    with pytest.raises(ConfigError):
        DriftConfig(**kwargs)


def test_bad_inputs_are_refused():
    with pytest.raises(ConfigError):
        WorldConfig(blocks_per_side=3)
    with pytest.raises(ConfigError):
        SyntheticWorld.from_seed(-1)
    with pytest.raises(ConfigError):
        simulate_odometry(np.zeros((5, 2)))
