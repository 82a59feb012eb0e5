"""The built-in synthetic street world: a procedural city block grid rendered as rectified stereo.

Pure numpy + OpenCV, deterministic for a seed. The scene is a Manhattan grid of blocks; each block is
two rows of box-shaped buildings with procedural facade textures (:mod:`recorders.synthetic_textures`),
on a textured ground plane (asphalt, markings, sidewalks) under a sky panorama. **Perceptual aliasing
is built in on purpose**: facade textures are drawn from a small bank, so the same facade appears in
many places, and a few whole street faces (a row of buildings with their widths, heights and textures)
are cloned onto other blocks. Place recognition therefore produces false positives.

Frames and conventions
----------------------
* World frame ``world``: x east, y north, z up, metres; intersection ``(i, j)`` of the street grid is
  at ``(i * pitch, j * pitch)``.
* Body frame (REP-103): x forward, y left, z up; planar pose ``T_world_body = (x_m, y_m, yaw_rad)``.
  The body origin is on the ground directly below the **left** camera.
* Camera optical frames (OpenCV): z forward, x right, y down. ``T_body_camera_left`` is the rotation
  :data:`R_BODY_CAMERA` (body x = camera z, body y = -camera x, body z = -camera y) with translation
  ``(0, 0, camera_height_m)``; the right camera is at ``(0, -baseline_m, camera_height_m)``. The
  cameras are level (no pitch or roll), so the horizon is the image row ``cy``.
* Rendering is an exact pinhole projection of textured planes: a point at depth ``Z`` (camera z) has
  disparity ``fx * baseline_m / Z`` between the rectified left and right images, and
  :meth:`SyntheticWorld.render_view` can return the depth map it rendered.

Rendering method
----------------
Sky (panorama lookup by ray azimuth/elevation) and ground (per-pixel ray/plane intersection, a
periodic street tile sampled with ``cv2.remap`` from a mip level chosen per band of rows) form the
background. Walls are vertical rectangles; with a level camera the depth of a wall is constant down
each image column and its inverse depth is affine in the column, so each wall is clipped exactly in
its parameter (near plane and the side planes of the frustum), split where its depth doubles (one mip
level per piece), warped with ``cv2.warpPerspective`` (the plane-induced homography) into the box
of its still-visible pixels and composited with a per-pixel inverse-depth buffer, nearest pieces
first; a per-column occlusion horizon skips pieces hidden behind nearer, taller walls before any
pixel work. Walls never occlude ground in front of them and are never hidden by it, so the depth
test is needed among walls only.
"""

from __future__ import annotations

import functools
import math
import threading
from dataclasses import dataclass, field

import cv2
import numpy as np

from lcv_replay.errors import ConfigError, require
from lcv_replay.records import Pose2D, StereoCalibration
from recorders.synthetic_textures import (
    SKY_MAX_ELEVATION_RAD,
    FacadeSpec,
    make_facade_spec,
    pole_spec,
    render_facade,
    render_sky,
    render_street_tile,
)

#: ``R_body_camera``: camera x right, y down, z forward -> body x forward, y left, z up.
R_BODY_CAMERA = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])


def t_body_camera(config: "WorldConfig | None" = None, camera: str = "left") -> np.ndarray:
    """``(4, 4)`` pose ``T_body_camera`` of the left (or right) camera's optical frame in the body frame."""
    if camera not in ("left", "right"):
        raise ConfigError(f"camera {camera!r} is not 'left' or 'right'", fix="use 'left' or 'right'")
    config = config or WorldConfig()
    T = np.eye(4)
    T[:3, :3] = R_BODY_CAMERA
    T[:3, 3] = (0.0, 0.0 if camera == "left" else -config.baseline_m, config.camera_height_m)
    return T


_MIP_LEVELS = 7
_NEAR_PLANE_M = 0.3


@dataclass(frozen=True)
class WorldConfig:
    """Size and look of the synthetic world.

    Attributes:
        blocks_per_side: blocks along x and along y (>= 5: the route needs a 4x4 grid of
            intersections with buildings on both sides of every street it drives).
        block_pitch_m: distance between neighbouring intersections.
        street_width_m: building line to building line across a street.
        road_width_m: kerb to kerb (two lanes); the rest of the street is sidewalk.
        facade_textures: street facade textures in the bank; every street-facing wall draws one, so
            with ~250 street walls each texture appears in several places (aliasing).
        side_textures: plain side/back-wall textures.
        cloned_street_faces: rows of buildings copied, with widths, heights and textures, onto
            other blocks facing the same way (strong aliasing of whole views).
        alley_probability: chance of a 3-5 m gap after a building.
        lamp_spacing_m: spacing of the lamp posts along the sidewalks (0: none).
        texture_px_per_m, ground_px_per_m: texel densities of walls and ground.
        texture_width_m, texture_height_m: size of one facade texture; buildings are no wider and no
            taller.
        camera_height_m, baseline_m: stereo rig (cf. KITTI: 1.65 m, 0.54 m).
        focal_ratio: ``fx = fy = focal_ratio * width_px`` (0.6 gives an 80 deg horizontal field of view).
        fog_distance_m: e-folding distance of the haze that blends far surfaces into the sky colour.
    """

    blocks_per_side: int = 5
    block_pitch_m: float = 60.0
    street_width_m: float = 16.0
    road_width_m: float = 10.0
    facade_textures: int = 48
    side_textures: int = 8
    cloned_street_faces: int = 3
    alley_probability: float = 0.15
    lamp_spacing_m: float = 24.0
    texture_px_per_m: float = 32.0
    ground_px_per_m: float = 25.0
    texture_width_m: float = 24.0
    texture_height_m: float = 24.0
    camera_height_m: float = 1.6
    baseline_m: float = 0.5
    focal_ratio: float = 0.6
    fog_distance_m: float = 700.0

    def __post_init__(self) -> None:
        require(self.blocks_per_side >= 5, "blocks_per_side", self.blocks_per_side, ">= 5")
        require(self.block_pitch_m - self.street_width_m >= 30.0, "block_pitch_m", self.block_pitch_m, "at least street_width_m + 30")
        require(0 < self.road_width_m < self.street_width_m, "road_width_m", self.road_width_m, "0 < road_width_m < street_width_m")
        require(self.facade_textures >= 2, "facade_textures", self.facade_textures, ">= 2")
        require(self.side_textures >= 1, "side_textures", self.side_textures, ">= 1")
        require(self.cloned_street_faces >= 0, "cloned_street_faces", self.cloned_street_faces, ">= 0")
        require(0.0 <= self.alley_probability < 1.0, "alley_probability", self.alley_probability, "[0, 1)")
        require(self.lamp_spacing_m == 0 or self.lamp_spacing_m >= 5.0, "lamp_spacing_m", self.lamp_spacing_m, "0 (none) or >= 5 m")
        require(self.texture_px_per_m >= 4 and self.ground_px_per_m >= 4, "texture_px_per_m", self.texture_px_per_m, ">= 4 texels per metre")
        require(self.texture_height_m >= 8.0 and self.texture_width_m >= 10.0, "texture_height_m", self.texture_height_m, ">= 8 m (width >= 10 m)")
        require(0.5 <= self.camera_height_m < 5.0, "camera_height_m", self.camera_height_m, "0.5 .. 5 m")
        require(self.baseline_m > 0, "baseline_m", self.baseline_m, "> 0")
        require(0.2 <= self.focal_ratio <= 3.0, "focal_ratio", self.focal_ratio, "0.2 .. 3")
        require(self.fog_distance_m > 0, "fog_distance_m", self.fog_distance_m, "> 0")


@dataclass(frozen=True)
class Walls:
    """All building walls of a world, as parallel arrays over ``M`` walls.

    A wall is the vertical rectangle above the ground segment ``a_xy -> b_xy`` (world metres), from
    0 to ``height_m``. Its outward normal is ``(d_y, -d_x)`` for the unit direction ``d`` from ``a``
    to ``b`` (footprints are counter-clockwise), and its texture runs left to right from ``a`` to ``b``
    as seen from outside.

    Attributes:
        a_xy, b_xy: ``(M, 2)`` float64 end points.
        height_m: ``(M,)`` float64.
        texture_id: ``(M,)`` int64 index into :attr:`SyntheticWorld.facade_specs`.
        gain: ``(M,)`` float32 brightness (orientation to the sun times a per-building tint).
        street_facing: ``(M,)`` bool, the wall lies on a block boundary (faces a street).
        building_id: ``(M,)`` int64; -1 for lamp posts.
        face_id: ``(M,)`` int64 street face (block row) of the wall's building, see
            :attr:`SyntheticWorld.street_faces`; -1 for lamp posts.
    """

    a_xy: np.ndarray
    b_xy: np.ndarray
    height_m: np.ndarray
    texture_id: np.ndarray
    gain: np.ndarray
    street_facing: np.ndarray
    building_id: np.ndarray
    face_id: np.ndarray

    def __len__(self) -> int:
        return len(self.height_m)

    @property
    def length_m(self) -> np.ndarray:
        return np.linalg.norm(self.b_xy - self.a_xy, axis=1)

    @property
    def centre_xy(self) -> np.ndarray:
        return 0.5 * (self.a_xy + self.b_xy)


@dataclass(frozen=True)
class StreetFace:
    """One row of buildings facing a street (a block's south or north half).

    Attributes:
        face_id: index in :attr:`SyntheticWorld.street_faces`.
        block: ``(bi, bj)`` block index (block ``(bi, bj)`` lies between intersections ``(bi, bj)``
            and ``(bi + 1, bj + 1)``).
        facing: ``"south"`` or ``"north"``.
        centre_xy: centre of its street-facing building line, world metres.
        cloned_from: the face whose buildings this face copies, or ``None``.
    """

    face_id: int
    block: tuple[int, int]
    facing: str
    centre_xy: tuple[float, float]
    cloned_from: int | None = None


@dataclass
class _ViewGeometry:
    """Per-resolution constants of the level pinhole camera (computed once per image size)."""

    calibration: StereoCalibration
    horizon_row: int  # first ground row (rows >= horizon_row look below the horizon)
    ground_depth_m: np.ndarray  # (H - horizon_row,) float32 camera-z depth of the ground per row
    ray_x: np.ndarray  # (W,) float32 (u - cx) / fx
    ground_bands: list[tuple[int, int, int, float]]  # (row0, row1 exclusive, mip level, mean depth) in ground rows
    sky_rows: np.ndarray  # (horizon_row, W) float32 panorama row per sky pixel
    sky_azimuth_rad: np.ndarray  # (W,) float32 azimuth of each column relative to the heading (CCW)
    columns: np.ndarray = field(repr=False)  # (W,) float32 0..W-1
    rows: np.ndarray = field(repr=False)  # (H,) float32 0..H-1


class SyntheticWorld:
    """A procedural street world that renders rectified stereo pairs from planar body poses.

    Build one with :meth:`from_seed`. Rendering is thread-safe: textures are generated lazily under a
    lock, and every render uses its own buffers.
    """

    def __init__(self, seed: int, config: WorldConfig, walls: Walls, facade_specs: tuple[FacadeSpec, ...], street_faces: tuple[StreetFace, ...]):
        self.seed = int(seed)
        self.config = config
        self.walls = walls
        self.facade_specs = facade_specs
        self.street_faces = street_faces
        self._lock = threading.Lock()
        self._textures: dict[int, list[np.ndarray]] = {}
        self._ground: list[np.ndarray] | None = None
        self._sky: np.ndarray | None = None
        self._views: dict[tuple[int, int], _ViewGeometry] = {}

    # -----------------------------------------------------------------------------------------
    # Construction
    # -----------------------------------------------------------------------------------------

    @classmethod
    def from_seed(cls, seed: int = 0, config: WorldConfig | None = None) -> "SyntheticWorld":
        """Generate the world's layout for ``seed`` (textures are drawn lazily when first seen).

        Args:
            seed: any non-negative integer; the same seed and config give the same world.
            config: size and look; :class:`WorldConfig` defaults when ``None``.
        """
        if int(seed) < 0:
            raise ConfigError(f"seed {seed} is negative", fix="use a seed >= 0")
        config = config or WorldConfig()
        rng = np.random.default_rng([int(seed), 0x5EED])
        n_facade = config.facade_textures
        specs = [make_facade_spec(rng, k, side=False) for k in range(n_facade)]
        specs += [make_facade_spec(rng, n_facade + k, side=True) for k in range(config.side_textures)]
        specs.append(pole_spec(len(specs), int(rng.integers(2**31 - 1))))
        walls, faces = _build_city(rng, config, tuple(specs))
        return cls(seed, config, walls, tuple(specs), faces)

    # -----------------------------------------------------------------------------------------
    # Camera
    # -----------------------------------------------------------------------------------------

    def calibration(self, width_px: int = 640, height_px: int = 480) -> StereoCalibration:
        """The rectified stereo calibration of the rig at this image size (pixel centres at integers)."""
        _check_size(width_px, height_px)
        f = self.config.focal_ratio * width_px
        return StereoCalibration(
            width_px=int(width_px),
            height_px=int(height_px),
            fx_px=f,
            fy_px=f,
            cx_px=(width_px - 1) / 2.0,
            cy_px=(height_px - 1) / 2.0,
            baseline_m=self.config.baseline_m,
            frame_id="camera_left",
        )

    def camera_positions(self, T_world_body: Pose2D) -> tuple[tuple[float, float], tuple[float, float]]:
        """World ``(x, y)`` of the left and right camera centres (both at ``camera_height_m``)."""
        x, y, yaw = (float(v) for v in T_world_body)
        b = self.config.baseline_m
        return (x, y), (x + b * math.sin(yaw), y - b * math.cos(yaw))

    # -----------------------------------------------------------------------------------------
    # Rendering
    # -----------------------------------------------------------------------------------------

    def render_stereo(self, T_world_body: Pose2D, *, width_px: int = 640, height_px: int = 480) -> tuple[np.ndarray, np.ndarray]:
        """Render the rectified stereo pair seen from the body pose ``T_world_body``.

        Returns:
            ``(left, right)``, each ``(height_px, width_px, 3)`` uint8 RGB.
        """
        pose = _check_pose(T_world_body)
        view = self._view(width_px, height_px)
        sky = self._render_sky(view, pose.yaw_rad)  # at infinity: the same in both cameras
        left = self._render(view, pose, 0, sky)[0]
        right = self._render(view, pose, 1, sky)[0]
        return left, right

    def render_view(self, T_world_body: Pose2D, camera: str = "left", *, width_px: int = 640, height_px: int = 480, with_depth: bool = False) -> tuple[np.ndarray, np.ndarray | None]:
        """Render one camera of the rig.

        Args:
            T_world_body: planar body pose in the world frame.
            camera: ``"left"`` or ``"right"``.
            width_px, height_px: image size.
            with_depth: also return the rendered depth.

        Returns:
            ``(image, depth)``: ``(H, W, 3)`` uint8 RGB, and ``(H, W)`` float32 camera-z depth in
            metres (``inf`` for sky) when ``with_depth``, else ``None``.
        """
        if camera not in ("left", "right"):
            raise ConfigError(f"camera {camera!r} is not 'left' or 'right'", fix="use 'left' or 'right'")
        pose = _check_pose(T_world_body)
        view = self._view(width_px, height_px)
        image, inv_depth = self._render(view, pose, 0 if camera == "left" else 1, self._render_sky(view, pose.yaw_rad))
        if not with_depth:
            return image, None
        depth = np.full((height_px, width_px), np.inf, np.float32)
        depth[view.horizon_row :] = view.ground_depth_m[:, None]
        hit = inv_depth > 0
        depth[hit] = 1.0 / inv_depth[hit]
        return image, depth

    def _render(self, view: _ViewGeometry, pose: Pose2D, camera_index: int, sky: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        calib = view.calibration
        centre = self.camera_positions(pose)[camera_index]
        image = np.empty((calib.height_px, calib.width_px, 3), np.uint8)
        image[: view.horizon_row] = sky
        self._draw_ground(image, view, centre, pose.yaw_rad)
        inv_depth = np.zeros((calib.height_px, calib.width_px), np.float32)
        self._draw_walls(image, inv_depth, view, centre, pose.yaw_rad)
        return image, inv_depth

    def _view(self, width_px: int, height_px: int) -> _ViewGeometry:
        key = (int(width_px), int(height_px))
        view = self._views.get(key)
        if view is None:
            view = _make_view(self.calibration(*key), self.config, self._ground_levels()[0].shape[0], self._sky_panorama().shape[0])
            with self._lock:
                self._views[key] = view
        return view

    def _render_sky(self, view: _ViewGeometry, yaw_rad: float) -> np.ndarray:
        """The sky rows ``(horizon_row, W, 3)`` for heading ``yaw_rad``."""
        sky = self._sky_panorama()
        width = sky.shape[1]
        cols = ((yaw_rad + view.sky_azimuth_rad) % (2 * math.pi)) * (width / (2 * math.pi))
        map_x = np.ascontiguousarray(np.broadcast_to(cols.astype(np.float32), view.sky_rows.shape))
        if view.horizon_row == 0:
            return np.empty((0, view.calibration.width_px, 3), np.uint8)
        return cv2.remap(sky, map_x, view.sky_rows, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)

    def _draw_ground(self, image: np.ndarray, view: _ViewGeometry, centre: tuple[float, float], yaw_rad: float) -> None:
        levels = self._ground_levels()
        cfg = self.config
        pitch = cfg.block_pitch_m
        ppm = cfg.ground_px_per_m
        c, s = math.cos(yaw_rad), math.sin(yaw_rad)
        # A ground ray through column u at depth Z hits  centre + Z * (forward + ray_x * right),
        # forward = (c, s), right = (s, -c). Tile texel = (point + P/2) * ppm - 0.5; the tile is
        # periodic, so the camera position is reduced modulo P and remap wraps (BORDER_WRAP).
        dir_x = (c + view.ray_x * s).astype(np.float32)
        dir_y = (s - view.ray_x * c).astype(np.float32)
        origin_x = (centre[0] + pitch / 2) % pitch
        origin_y = (centre[1] + pitch / 2) % pitch
        ground = image[view.horizon_row :]
        for row0, row1, level, depth_m in view.ground_bands:
            scale = ppm / (1 << level)
            z = view.ground_depth_m[row0:row1, None]
            mx = z * (dir_x * scale)[None, :] + np.float32(origin_x * scale - 0.5 / (1 << level))
            my = z * (dir_y * scale)[None, :] + np.float32(origin_y * scale - 0.5 / (1 << level))
            band = cv2.remap(levels[level], mx, my, cv2.INTER_LINEAR, borderMode=cv2.BORDER_WRAP)
            fog = 1.0 - math.exp(-depth_m / cfg.fog_distance_m)
            if fog > 0.01:
                band = cv2.convertScaleAbs(band, alpha=1.0 - fog, beta=_FOG_GREY * fog)
            ground[row0:row1] = band

    def _draw_walls(self, image: np.ndarray, inv_depth: np.ndarray, view: _ViewGeometry, centre: tuple[float, float], yaw_rad: float) -> None:
        pieces = _wall_pieces(self.walls, self.config, view, centre, yaw_rad)
        cy = view.calibration.cy_px
        fy = view.calibration.fy_px
        hc = self.config.camera_height_m
        # Nearest first: the inverse-depth test then rejects hidden pixels before any warping, and
        # each warp is limited to the box of the piece's still-visible pixels. Per column we also
        # keep the highest top edge and the farthest inverse depth of the pieces drawn so far: every
        # wall reaches down to its ground line, so a piece farther than all of them and lower than
        # the highest is hidden in that column (a conservative test on 1-D arrays).
        width_px = view.calibration.width_px
        occ_top = np.full(width_px, np.inf, np.float32)
        occ_inv_z = np.full(width_px, np.inf, np.float32)
        order = np.argsort(-np.maximum(pieces.inv_z0, pieces.inv_z0 + pieces.inv_z_slope * (pieces.box[:, 1] - pieces.u0)))
        for k in order:
            c0, c1, r0, r1 = (int(v) for v in pieces.box[k])
            box_c0, box_r0 = c0, r0  # origin of the piece's homography
            inv_z = (pieces.inv_z0[k] + (view.columns[c0:c1] - pieces.u0[k]) * pieces.inv_z_slope[k]).astype(np.float32)
            top = cy - fy * (pieces.height_m[k] - hc) * inv_z
            hidden = (top >= occ_top[c0:c1]) & (inv_z < occ_inv_z[c0:c1])
            np.minimum(occ_top[c0:c1], top, out=occ_top[c0:c1])
            np.minimum(occ_inv_z[c0:c1], inv_z, out=occ_inv_z[c0:c1])
            open_cols = np.flatnonzero(~hidden)
            if len(open_cols) == 0:
                continue
            ca, cb = int(open_cols[0]), int(open_cols[-1]) + 1
            c0, c1, inv_z, top = c0 + ca, c0 + cb, inv_z[ca:cb], top[ca:cb]
            r0 = max(r0, int(math.ceil(float(top.min()))))
            if r1 <= r0:
                continue
            rows = view.rows[r0:r1, None]
            mask = rows >= top
            mask &= rows <= cy + fy * hc * inv_z
            mask &= inv_z > inv_depth[r0:r1, c0:c1]
            row_hit = np.flatnonzero(mask.any(axis=1))
            if len(row_hit) == 0:
                continue
            col_hit = np.flatnonzero(mask.any(axis=0))
            ra, rb, ca, cb = int(row_hit[0]), int(row_hit[-1]) + 1, int(col_hit[0]), int(col_hit[-1]) + 1
            levels = self._facade_levels(int(pieces.texture_id[k]))
            level = min(int(pieces.level[k]), len(levels) - 1)
            R0, R1, C0, C1 = r0 + ra, r0 + rb, c0 + ca, c0 + cb  # the patch, in image pixels
            H = pieces.homography[k].copy()
            H[:, :2] *= float(1 << level)
            H[0] -= (C0 - box_c0) * H[2]
            H[1] -= (R0 - box_r0) * H[2]
            patch = cv2.warpPerspective(levels[level], H, (C1 - C0, R1 - R0), flags=cv2.INTER_LINEAR, borderMode=cv2.BORDER_REPLICATE)
            patch = cv2.convertScaleAbs(patch, alpha=float(pieces.alpha[k]), beta=float(pieces.beta[k]))
            mask_u8 = mask.view(np.uint8)[ra:rb, ca:cb]
            cv2.copyTo(patch, mask_u8, image[R0:R1, C0:C1])
            cv2.copyTo(cv2.repeat(inv_z[None, ca:cb], R1 - R0, 1), mask_u8, inv_depth[R0:R1, C0:C1])

    # -----------------------------------------------------------------------------------------
    # Lazily generated textures
    # -----------------------------------------------------------------------------------------

    def facade_texture(self, texture_id: int) -> np.ndarray:
        """Full-resolution texture ``texture_id``: ``(H, W, 3)`` uint8 RGB (ground-anchored)."""
        return self._facade_levels(texture_id)[0]

    def _facade_levels(self, texture_id: int) -> list[np.ndarray]:
        levels = self._textures.get(texture_id)
        if levels is None:
            cfg = self.config
            levels = list(_facade_pyramid(self.facade_specs[texture_id], cfg.texture_width_m, cfg.texture_height_m, cfg.texture_px_per_m))
            with self._lock:
                levels = self._textures.setdefault(texture_id, levels)
        return levels

    def _ground_levels(self) -> list[np.ndarray]:
        if self._ground is None:
            cfg = self.config
            levels = list(_street_pyramid(self.seed * 7919 + 17, cfg.block_pitch_m, cfg.road_width_m / 2, cfg.street_width_m / 2, cfg.ground_px_per_m))
            with self._lock:
                if self._ground is None:
                    self._ground = levels
        return self._ground  # type: ignore[return-value]

    def _sky_panorama(self) -> np.ndarray:
        if self._sky is None:
            sky = _sky_pixels(self.seed * 104729 + 3)
            with self._lock:
                if self._sky is None:
                    self._sky = sky
        return self._sky  # type: ignore[return-value]


_FOG_GREY = 205.0


def _check_size(width_px: int, height_px: int) -> None:
    if not (16 <= int(width_px) <= 8192 and 16 <= int(height_px) <= 8192):
        raise ConfigError(f"image size {width_px}x{height_px} is out of range", fix="use 16..8192 pixels per side, e.g. 640x480")


# Textures depend only on their spec and size, so they are shared between worlds of one process
# (tests, benchmarks and repeated recordings regenerate nothing). Cached arrays are read-only.
@functools.lru_cache(maxsize=128)
def _facade_pyramid(spec: FacadeSpec, width_m: float, height_m: float, px_per_m: float) -> tuple[np.ndarray, ...]:
    return _read_only(_pyramid(render_facade(spec, width_m, height_m, px_per_m)))


@functools.lru_cache(maxsize=4)
def _street_pyramid(seed: int, pitch_m: float, road_half_width_m: float, building_line_m: float, px_per_m: float) -> tuple[np.ndarray, ...]:
    return _read_only(_pyramid(render_street_tile(seed, pitch_m, road_half_width_m, building_line_m, px_per_m), wrap=True))


@functools.lru_cache(maxsize=4)
def _sky_pixels(seed: int) -> np.ndarray:
    return _read_only([render_sky(seed)])[0]


def _read_only(arrays: list[np.ndarray]) -> tuple[np.ndarray, ...]:
    for array in arrays:
        array.flags.writeable = False
    return tuple(arrays)


def _pyramid(image: np.ndarray, *, wrap: bool = False) -> list[np.ndarray]:
    """Mip levels by ``cv2.pyrDown``: level ``k`` texel ``i`` sits at level-0 texel ``2^k i``."""
    levels = [image]
    border = cv2.BORDER_WRAP if wrap else cv2.BORDER_REFLECT_101
    while len(levels) < _MIP_LEVELS and min(levels[-1].shape[:2]) >= 8:
        if wrap:
            # pyrDown has no BORDER_WRAP: pad periodically, reduce, crop.
            pad = 4
            padded = cv2.copyMakeBorder(levels[-1], pad, pad, pad, pad, cv2.BORDER_WRAP)
            reduced = cv2.pyrDown(padded)
            h, w = (levels[-1].shape[0] + 1) // 2, (levels[-1].shape[1] + 1) // 2
            levels.append(np.ascontiguousarray(reduced[pad // 2 : pad // 2 + h, pad // 2 : pad // 2 + w]))
        else:
            levels.append(cv2.pyrDown(levels[-1], borderType=border))
    return levels


def _check_pose(T_world_body: Pose2D) -> Pose2D:
    pose = Pose2D(*(float(v) for v in T_world_body))
    if not all(math.isfinite(v) for v in pose):
        raise ConfigError(f"pose {tuple(pose)} is not finite", fix="pass a finite (x_m, y_m, yaw_rad)")
    return pose


@dataclass(frozen=True)
class _Pieces:
    """Visible wall pieces of one view, as parallel arrays over ``P`` pieces.

    ``box`` is ``(P, 4)`` int ``(c0, c1, r0, r1)`` (end-exclusive pixel box); ``homography`` is
    ``(P, 3, 3)``: level-0 texel -> box pixel; column ``u`` has inverse depth
    ``inv_z0 + (u - u0) * inv_z_slope``; ``alpha``/``beta`` are the brightness gain and haze offset.
    """

    wall: np.ndarray
    texture_id: np.ndarray
    height_m: np.ndarray
    box: np.ndarray
    homography: np.ndarray
    level: np.ndarray
    u0: np.ndarray
    inv_z0: np.ndarray
    inv_z_slope: np.ndarray
    alpha: np.ndarray
    beta: np.ndarray


def _wall_pieces(walls: Walls, cfg: WorldConfig, view: _ViewGeometry, centre: tuple[float, float], yaw_rad: float) -> _Pieces:
    """Cull, clip and split the walls for one camera (vectorised over walls and pieces).

    Each wall's parameter ``t`` in ``[0, 1]`` (from ``a`` to ``b``) is clipped exactly to the near
    plane and to the side planes of the frustum (depth and lateral offset are affine in ``t``), and the
    clipped range is split where the depth doubles, so one texture mip level suits each piece.
    """
    calib = view.calibration
    fx, fy, cx, cy = calib.fx_px, calib.fy_px, calib.cx_px, calib.cy_px
    width_px, height_px = calib.width_px, calib.height_px
    hc = cfg.camera_height_m
    c, s = math.cos(yaw_rad), math.sin(yaw_rad)
    fwd = np.array([c, s])
    right = np.array([s, -c])
    rel_a = walls.a_xy - np.asarray(centre)
    rel_b = walls.b_xy - np.asarray(centre)
    xa, za = rel_a @ right, rel_a @ fwd
    dx, dz = rel_b @ right - xa, rel_b @ fwd - za
    d = walls.b_xy - walls.a_xy
    facing = rel_a[:, 0] * d[:, 1] - rel_a[:, 1] * d[:, 0] < 0  # camera on the outer side of the wall
    # Constraints a + b t >= 0: in front of the near plane, left of the right edge, right of the left edge.
    k_right = (width_px - 0.5 - cx) / fx
    k_left = (-0.5 - cx) / fx
    t_lo = np.zeros(len(walls))
    t_hi = np.where(facing, 1.0, -1.0)
    for a, b in ((za - _NEAR_PLANE_M, dz), (k_right * za - xa, k_right * dz - dx), (xa - k_left * za, dx - k_left * dz)):
        with np.errstate(divide="ignore", invalid="ignore"):
            root = -a / b
        t_lo = np.where(b > 0, np.maximum(t_lo, root), t_lo)
        t_hi = np.where(b < 0, np.minimum(t_hi, root), t_hi)
        t_hi = np.where((b == 0) & (a < 0), -1.0, t_hi)
    vis = np.flatnonzero(t_hi > t_lo + 1e-9)
    # Split each visible range into pieces of depth ratio <= 2 (geometric steps in depth).
    z_lo = za[vis] + t_lo[vis] * dz[vis]
    z_hi = za[vis] + t_hi[vis] * dz[vis]
    n = np.clip(np.ceil(np.log2(np.maximum(z_lo, z_hi) / np.minimum(z_lo, z_hi)) - 1e-9), 1, 8).astype(np.int64)
    wall = np.repeat(vis, n)
    first = np.repeat(np.cumsum(n) - n, n)
    k = np.arange(len(wall)) - first
    nn = np.repeat(n, n).astype(np.float64)
    zl, zh = np.repeat(z_lo, n), np.repeat(z_hi, n)
    tl, th = t_lo[wall], t_hi[wall]
    dz_w = dz[wall]
    steep = np.abs(dz_w) > 1e-9
    with np.errstate(divide="ignore", invalid="ignore"):
        ta = np.where(steep, (zl * (zh / zl) ** (k / nn) - za[wall]) / dz_w, tl + (th - tl) * k / nn)
        tb = np.where(steep, (zl * (zh / zl) ** ((k + 1) / nn) - za[wall]) / dz_w, tl + (th - tl) * (k + 1) / nn)
    ta = np.where(k == 0, tl, ta)
    tb = np.where(k == nn - 1, th, tb)
    za_p, zb_p = za[wall] + ta * dz_w, za[wall] + tb * dz_w
    ua = cx + fx * (xa[wall] + ta * dx[wall]) / za_p
    ub = cx + fx * (xa[wall] + tb * dx[wall]) / zb_p
    swap = ua > ub
    ua, ub = np.where(swap, ub, ua), np.where(swap, ua, ub)
    za_p, zb_p = np.where(swap, zb_p, za_p), np.where(swap, za_p, zb_p)
    iza, izb = 1.0 / za_p, 1.0 / zb_p
    height = walls.height_m[wall]
    c0 = np.maximum(0, np.ceil(ua)).astype(np.int64)
    c1 = np.minimum(width_px, np.ceil(ub)).astype(np.int64)  # column u is drawn when ua <= u < ub
    iz_max, iz_min = np.maximum(iza, izb), np.minimum(iza, izb)
    top = np.where(height > hc, cy - fy * (height - hc) * iz_max, cy - fy * (height - hc) * iz_min)
    r0 = np.maximum(0, np.ceil(top)).astype(np.int64)
    r1 = np.minimum(height_px, np.floor(cy + fy * hc * iz_max) + 1).astype(np.int64)
    keep = (c1 > c0) & (r1 > r0)
    # Mip level: texel footprint of a pixel, geometric mean of the two axes.
    ppm = cfg.texture_px_per_m
    length = np.linalg.norm(d[wall], axis=1)
    texels_u = np.abs(tb - ta) * length * ppm / np.maximum(ub - ua, 1e-6)
    texels_v = ppm * 2.0 / (fy * (iza + izb))
    level = np.clip(np.floor(0.5 * np.log2(np.maximum(texels_u * texels_v, 1e-12)) + 0.5), 0, _MIP_LEVELS - 1).astype(np.int64)
    fog = 1.0 - np.exp(-2.0 / ((iza + izb) * cfg.fog_distance_m))
    # Homography level-0 texel (col, row) -> box pixel: K [unit.right/ppm, 0, xa; 0, 1/ppm, hc - H;
    # unit.fwd/ppm, 0, za], then shifted by the box origin.
    unit = d[wall] / length[:, None]
    M = np.zeros((len(wall), 3, 3))
    M[:, 0, 0] = unit @ right / ppm
    M[:, 0, 2] = xa[wall]
    M[:, 1, 1] = 1.0 / ppm
    M[:, 1, 2] = hc - cfg.texture_height_m
    M[:, 2, 0] = unit @ fwd / ppm
    M[:, 2, 2] = za[wall]
    shift_K = np.zeros((len(wall), 3, 3))
    shift_K[:, 0, 0] = fx
    shift_K[:, 0, 2] = cx - c0
    shift_K[:, 1, 1] = fy
    shift_K[:, 1, 2] = cy - r0
    shift_K[:, 2, 2] = 1.0
    H = shift_K @ M
    return _Pieces(
        wall=wall[keep],
        texture_id=walls.texture_id[wall][keep],
        height_m=height[keep],
        box=np.stack([c0, c1, r0, r1], axis=1)[keep],
        homography=H[keep],
        level=level[keep],
        u0=ua[keep],
        inv_z0=iza[keep],
        inv_z_slope=((izb - iza) / np.maximum(ub - ua, 1e-9))[keep],
        alpha=(walls.gain[wall] * (1.0 - fog))[keep],
        beta=(_FOG_GREY * fog)[keep],
    )


def _make_view(calib: StereoCalibration, config: WorldConfig, ground_tile_px: int, sky_height_px: int) -> _ViewGeometry:
    width, height = calib.width_px, calib.height_px
    fx, fy, cx, cy = calib.fx_px, calib.fy_px, calib.cx_px, calib.cy_px
    hc = config.camera_height_m
    horizon_row = int(math.floor(cy)) + 1  # first row strictly below the horizon
    rows = np.arange(horizon_row, height, dtype=np.float64)
    depth = fy * hc / (rows - cy)
    # Texel footprint of a pixel on the ground: across ~ Z / fx, along ~ Z^2 / (fy h).
    footprint = np.sqrt((depth / fx) * (depth * depth / (fy * hc))) * config.ground_px_per_m
    max_level = len(_pyramid_sizes(ground_tile_px)) - 1
    level = np.clip(np.floor(np.log2(np.maximum(footprint, 1e-9)) + 0.5), 0, max_level).astype(int)
    bands: list[tuple[int, int, int, float]] = []
    start = 0
    for k in range(1, len(level) + 1):
        if k == len(level) or level[k] != level[start]:
            bands.append((start, k, int(level[start]), float(np.exp(np.mean(np.log(depth[start:k]))))))
            start = k
    cols = np.arange(width, dtype=np.float64)
    ray_x = (cols - cx) / fx
    sky_rows_px = np.arange(horizon_row, dtype=np.float64)
    elevation = np.arctan2(-(sky_rows_px[:, None] - cy) / fy, np.sqrt(1.0 + ray_x[None, :] ** 2))
    sky_rows = (1.0 - elevation / SKY_MAX_ELEVATION_RAD) * (sky_height_px - 1)
    return _ViewGeometry(
        calibration=calib,
        horizon_row=horizon_row,
        ground_depth_m=depth.astype(np.float32),
        ray_x=ray_x.astype(np.float32),
        ground_bands=bands,
        sky_rows=np.ascontiguousarray(sky_rows.astype(np.float32)),
        sky_azimuth_rad=np.arctan(-ray_x).astype(np.float32),
        columns=cols.astype(np.float32),
        rows=np.arange(height, dtype=np.float32),
    )


def _pyramid_sizes(size: int) -> list[int]:
    sizes = [size]
    while len(sizes) < _MIP_LEVELS and sizes[-1] >= 8:
        sizes.append((sizes[-1] + 1) // 2)
    return sizes


# ---------------------------------------------------------------------------------------------
# City layout
# ---------------------------------------------------------------------------------------------

_SUN_DIRECTION = np.array([-0.45, -0.89])  # unit vector towards the sun (from the south-south-west)


def _build_city(rng: np.random.Generator, cfg: WorldConfig, specs: tuple[FacadeSpec, ...]) -> tuple[Walls, tuple[StreetFace, ...]]:
    """Lay out blocks, rows of buildings and their walls, and clone a few street faces."""
    pitch = cfg.block_pitch_m
    half_street = cfg.street_width_m / 2
    first = -(cfg.blocks_per_side // 2)
    # A street face (block half-row) is a list of buildings (x0, x1, upper floors, texture, tint)
    # along x, or None for an alley.
    faces: list[StreetFace] = []
    rows: list[list[tuple[float, float, int, int, float]]] = []
    for bi in range(first, first + cfg.blocks_per_side):
        for bj in range(first, first + cfg.blocks_per_side):
            x0, x1 = bi * pitch + half_street, (bi + 1) * pitch - half_street
            y0, y1 = bj * pitch + half_street, (bj + 1) * pitch - half_street
            for facing, y_line in (("south", y0), ("north", y1)):
                faces.append(StreetFace(len(faces), (bi, bj), facing, ((x0 + x1) / 2, y_line)))
                rows.append(_draw_row(rng, cfg, specs, x1 - x0))
    # Clone whole rows between inner blocks facing the same way (the route drives past them).
    inner = [f.face_id for f in faces if all(-1 <= b <= 1 for b in f.block)]
    order = rng.permutation(inner)
    used: set[int] = set()
    clones = 0
    for src in order:
        if clones >= cfg.cloned_street_faces:
            break
        if int(src) in used:
            continue
        candidates = [
            int(f) for f in order
            if int(f) not in used and int(f) != int(src) and faces[int(f)].facing == faces[int(src)].facing
            and abs(faces[int(f)].block[0] - faces[int(src)].block[0]) + abs(faces[int(f)].block[1] - faces[int(src)].block[1]) >= 2
        ]
        if not candidates:
            continue
        dst = candidates[0]
        rows[dst] = list(rows[int(src)])
        faces[dst] = StreetFace(dst, faces[dst].block, faces[dst].facing, faces[dst].centre_xy, cloned_from=int(src))
        used.update((int(src), dst))
        clones += 1
    walls = _walls_from_rows(rng, cfg, specs, faces, rows)
    if cfg.lamp_spacing_m > 0:
        walls = _concat_walls(walls, _lamp_posts(rng, cfg, texture_id=len(specs) - 1))
    return walls, tuple(faces)


_POLE_SIZE_M = 0.25
_POLE_HEIGHT_M = 5.5


def _lamp_posts(rng: np.random.Generator, cfg: WorldConfig, texture_id: int) -> Walls:
    """Lamp posts: 0.25 m square boxes on every sidewalk, 0.5 m from the kerb, away from corners."""
    pitch = cfg.block_pitch_m
    half_street = cfg.street_width_m / 2
    offset = cfg.road_width_m / 2 + 0.5  # pole centre, from the street centre line
    first = -(cfg.blocks_per_side // 2)
    centres: list[tuple[float, float]] = []
    for bi in range(first, first + cfg.blocks_per_side):
        for bj in range(first, first + cfg.blocks_per_side):
            x0, x1 = bi * pitch + half_street, (bi + 1) * pitch - half_street
            y0, y1 = bj * pitch + half_street, (bj + 1) * pitch - half_street
            n = max(1, int((x1 - x0 - 16.0) // cfg.lamp_spacing_m) + 1)
            along = np.linspace(x0 + 8.0, x1 - 8.0, n) if n > 1 else np.array([(x0 + x1) / 2])
            for t in along + rng.uniform(-1.5, 1.5, size=len(along)):
                centres += [(t, bj * pitch + offset), (t, (bj + 1) * pitch - offset)]
            along_y = np.linspace(y0 + 8.0, y1 - 8.0, n) if n > 1 else np.array([(y0 + y1) / 2])
            for t in along_y + rng.uniform(-1.5, 1.5, size=len(along_y)):
                centres += [(bi * pitch + offset, t), ((bi + 1) * pitch - offset, t)]
    h = _POLE_SIZE_M / 2
    a_xy, b_xy = [], []
    for cx, cy in centres:
        corners = [(cx - h, cy - h), (cx + h, cy - h), (cx + h, cy + h), (cx - h, cy + h)]  # counter-clockwise
        for k in range(4):
            a_xy.append(corners[k])
            b_xy.append(corners[(k + 1) % 4])
    m = len(a_xy)
    d = np.subtract(b_xy, a_xy)
    normal = np.stack([d[:, 1], -d[:, 0]], axis=1) / _POLE_SIZE_M
    return Walls(
        a_xy=np.asarray(a_xy, np.float64),
        b_xy=np.asarray(b_xy, np.float64),
        height_m=np.full(m, _POLE_HEIGHT_M),
        texture_id=np.full(m, texture_id, np.int64),
        gain=(0.8 + 0.25 * np.maximum(0.0, normal @ _SUN_DIRECTION)).astype(np.float32),
        street_facing=np.zeros(m, bool),
        building_id=np.full(m, -1, np.int64),
        face_id=np.full(m, -1, np.int64),
    )


def _concat_walls(a: Walls, b: Walls) -> Walls:
    return Walls(**{name: np.concatenate([getattr(a, name), getattr(b, name)]) for name in Walls.__dataclass_fields__})


def _draw_row(rng: np.random.Generator, cfg: WorldConfig, specs: tuple[FacadeSpec, ...], x1: float) -> list[tuple[float, float, int, int, float]]:
    """Buildings ``(x_start, x_end, upper_floors, facade texture, tint)`` filling ``[0, x1]`` (block-relative)."""
    buildings: list[tuple[float, float, int, int, float]] = []
    x = 0.0
    max_w = min(20.0, cfg.texture_width_m)
    while x1 - x > 1e-6:
        width = float(rng.uniform(8.0, max_w))
        if x1 - (x + width) < 6.0:
            width = x1 - x
            if width > cfg.texture_width_m:  # split the remainder in two
                width = width / 2
        texture = int(rng.integers(cfg.facade_textures))
        spec = specs[texture]
        max_floors = max(1, int((cfg.texture_height_m - 0.7 - spec.ground_floor_m) / spec.floor_m))
        floors = int(rng.integers(1, max_floors + 1))
        buildings.append((x, x + width, floors, texture, float(rng.uniform(0.9, 1.08))))
        x += width
        if x1 - x > 14.0 and rng.random() < cfg.alley_probability:
            x += float(rng.uniform(3.0, 5.0))
    return buildings


def _walls_from_rows(rng: np.random.Generator, cfg: WorldConfig, specs: tuple[FacadeSpec, ...], faces: list[StreetFace], rows: list[list[tuple[float, float, int, int, float]]]) -> Walls:
    pitch = cfg.block_pitch_m
    half_street = cfg.street_width_m / 2
    n_facade = cfg.facade_textures
    a_xy: list[tuple[float, float]] = []
    b_xy: list[tuple[float, float]] = []
    heights: list[float] = []
    textures: list[int] = []
    gains: list[float] = []
    street: list[bool] = []
    building_ids: list[int] = []
    face_ids: list[int] = []
    building = 0

    def side_texture() -> int:
        return n_facade + int(rng.integers(cfg.side_textures))

    for face, row in zip(faces, rows):
        bi, bj = face.block
        x_block0, x_block1 = bi * pitch + half_street, (bi + 1) * pitch - half_street
        y0, y1 = bj * pitch + half_street, (bj + 1) * pitch - half_street
        y_mid = (y0 + y1) / 2
        ya, yb = (y0, y_mid) if face.facing == "south" else (y_mid, y1)
        for k, (xs_rel, xe_rel, floors, texture, tint) in enumerate(row):
            xs, xe = x_block0 + xs_rel, x_block0 + xe_rel
            height = specs[texture].height_for_floors(floors)
            prev = row[k - 1] if k > 0 else None
            nxt = row[k + 1] if k + 1 < len(row) else None
            # Counter-clockwise footprint: south, east, north, west walls.
            corners = [(xs, ya), (xe, ya), (xe, yb), (xs, yb)]
            for side in range(4):
                a, b = corners[side], corners[(side + 1) % 4]
                if side == 0:  # south
                    facing_street = face.facing == "south"
                elif side == 2:  # north
                    facing_street = face.facing == "north"
                elif side == 1:  # east
                    facing_street = abs(xe - x_block1) < 1e-6
                    if not facing_street and nxt is not None and abs(nxt[0] - xe_rel) < 1e-6 and specs[nxt[3]].height_for_floors(nxt[2]) >= height:
                        continue  # flush against an equal or taller neighbour: never visible
                else:  # west
                    facing_street = abs(xs - x_block0) < 1e-6
                    if not facing_street and prev is not None and abs(prev[1] - xs_rel) < 1e-6 and specs[prev[3]].height_for_floors(prev[2]) >= height:
                        continue
                if side in (0, 2):
                    tex = texture if facing_street else side_texture()
                else:
                    tex = int(rng.integers(n_facade)) if facing_street else side_texture()
                direction = np.subtract(b, a)
                normal = np.array([direction[1], -direction[0]]) / np.linalg.norm(direction)
                sun = 0.8 + 0.25 * max(0.0, float(normal @ _SUN_DIRECTION))
                a_xy.append(a)
                b_xy.append(b)
                heights.append(height)
                textures.append(tex)
                gains.append(sun * tint)
                street.append(facing_street)
                building_ids.append(building)
                face_ids.append(face.face_id)
            building += 1
    return Walls(
        a_xy=np.asarray(a_xy, np.float64),
        b_xy=np.asarray(b_xy, np.float64),
        height_m=np.asarray(heights, np.float64),
        texture_id=np.asarray(textures, np.int64),
        gain=np.asarray(gains, np.float32),
        street_facing=np.asarray(street, bool),
        building_id=np.asarray(building_ids, np.int64),
        face_id=np.asarray(face_ids, np.int64),
    )


# ---------------------------------------------------------------------------------------------
# The vehicle route
# ---------------------------------------------------------------------------------------------

#: One cycle of the route, as intersections ``(i, j)`` of the street grid, driven in order and then
#: repeated. It starts eastwards from (0, 0); the block loop (0,0)-(1,0)-(1,1)-(0,1) is revisited
#: in the same direction after 240 m, the streets (0,0)-(1,0) and (0,1)-(1,1) are revisited in the
#: opposite direction later in the cycle, and there are no U-turns. 26 legs (1,560 m at a 60 m pitch).
ROUTE_CYCLE: tuple[tuple[int, int], ...] = (
    (0, 0), (1, 0), (1, 1), (0, 1),  # block loop, counter-clockwise
    (0, 0), (1, 0), (2, 0), (2, 1), (1, 1), (0, 1),  # a wider loop sharing three streets with it
    (0, 0), (0, -1), (1, -1), (1, 0), (1, 1), (1, 2), (0, 2), (0, 1), (1, 1), (2, 1), (2, 0), (1, 0),  # opposite-direction pass
    (0, 0), (-1, 0), (-1, -1), (0, -1),  # back to the start heading north, then east again
)


@dataclass(frozen=True)
class RouteConfig:
    """How the vehicle drives the route (frame rate 10 Hz, so 1 m/frame is 36 km/h).

    Attributes:
        speed_m_per_frame: cruise speed on straight streets.
        lateral_accel_m_per_frame2: comfort limit in turns (0.035 m/frame^2 = 3.5 m/s^2 at 10 Hz).
        accel_m_per_frame2: braking and acceleration limit (0.02 = 2 m/s^2 at 10 Hz).
        lane_offset_m: distance of the driving line to the right of the street centre line.
        left_turn_radius_m, right_turn_radius_m: radii of the turning arcs.
        wobble_m: amplitude of the slow lateral weave within the lane.
    """

    speed_m_per_frame: float = 1.0
    lateral_accel_m_per_frame2: float = 0.035
    accel_m_per_frame2: float = 0.02
    lane_offset_m: float = 2.5
    left_turn_radius_m: float = 9.0
    right_turn_radius_m: float = 6.0
    wobble_m: float = 0.25

    def __post_init__(self) -> None:
        require(0.05 <= self.speed_m_per_frame <= 5.0, "speed_m_per_frame", self.speed_m_per_frame, "0.05 .. 5 m per frame")
        require(self.lateral_accel_m_per_frame2 > 0, "lateral_accel_m_per_frame2", self.lateral_accel_m_per_frame2, "> 0")
        require(self.accel_m_per_frame2 > 0, "accel_m_per_frame2", self.accel_m_per_frame2, "> 0")
        require(0 <= self.lane_offset_m < 4.0, "lane_offset_m", self.lane_offset_m, "0 .. 4 m")
        require(2.0 <= self.right_turn_radius_m <= 12.0 and 2.0 <= self.left_turn_radius_m <= 12.0, "right_turn_radius_m", self.right_turn_radius_m, "2 .. 12 m")
        require(0 <= self.wobble_m <= 1.0, "wobble_m", self.wobble_m, "0 .. 1 m")


def make_route(world: SyntheticWorld, frames: int, *, config: RouteConfig | None = None, seed: int | None = None) -> np.ndarray:
    """True body poses of the vehicle for ``frames`` frames along :data:`ROUTE_CYCLE`.

    The driving line keeps to the right lane, turns on circular arcs, weaves slightly, and the speed
    drops in the turns under a lateral-acceleration limit with bounded braking and acceleration.

    Args:
        world: the world whose street grid is driven.
        frames: number of poses ``N >= 1``.
        config: driving parameters; :class:`RouteConfig` defaults when ``None``.
        seed: seed of the weave phases; the world's seed when ``None``.

    Returns:
        ``(N, 3)`` float64 poses ``T_world_body`` as ``(x_m, y_m, yaw_rad)``, yaw wrapped to
        ``[-pi, pi)``.
    """
    if int(frames) < 1:
        raise ConfigError(f"frames = {frames} must be at least 1", fix="pass --frames 1 or more")
    cfg = config or RouteConfig()
    rng = np.random.default_rng([world.seed if seed is None else int(seed), 0xD1CE])
    step_m = 0.05
    needed_m = frames * cfg.speed_m_per_frame + 50.0
    cycle_m = len(ROUTE_CYCLE) * world.config.block_pitch_m
    cycles = int(math.ceil(needed_m / cycle_m))
    points = _driving_line(world.config.block_pitch_m, cfg, cycles, step_m)
    # Lateral weave along the normal: two slow sinusoids with random phases.
    heading = _headings(points)
    arclength = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    phases = rng.uniform(0, 2 * np.pi, size=2)
    offset = cfg.wobble_m * (0.7 * np.sin(2 * np.pi * arclength / 47.0 + phases[0]) + 0.3 * np.sin(2 * np.pi * arclength / 19.0 + phases[1]))
    points = points + offset[:, None] * np.stack([-np.sin(heading), np.cos(heading)], axis=1)
    heading = _headings(points)
    arclength = np.concatenate([[0.0], np.cumsum(np.linalg.norm(np.diff(points, axis=0), axis=1))])
    # Speed profile: v <= cruise, v^2 * curvature <= lateral limit, |dv^2/ds| <= 2 * accel.
    unwrapped = np.unwrap(heading)
    curvature = np.abs(np.gradient(unwrapped, arclength))
    curvature = np.convolve(curvature, np.ones(21) / 21, mode="same")
    v_max = np.minimum(cfg.speed_m_per_frame, np.sqrt(cfg.lateral_accel_m_per_frame2 / np.maximum(curvature, 1e-9)))
    # v(s_i)^2 <= v(s_j)^2 + 2 a |s_i - s_j| for all j: running minima forwards and backwards.
    two_a = 2.0 * cfg.accel_m_per_frame2
    v2 = v_max**2
    v2 = np.minimum(v2, two_a * arclength + np.minimum.accumulate(v2 - two_a * arclength))
    v2 = np.minimum(v2, -two_a * arclength + np.minimum.accumulate((v2 + two_a * arclength)[::-1])[::-1])
    speed = np.sqrt(v2)
    # Integrate the frame positions along the arc length (midpoint rule).
    s_frames = np.empty(int(frames))
    s = 0.0
    for k in range(int(frames)):
        s_frames[k] = s
        v0 = float(np.interp(s, arclength, speed))
        s += float(np.interp(s + 0.5 * v0, arclength, speed))
    poses = np.empty((int(frames), 3))
    poses[:, 0] = np.interp(s_frames, arclength, points[:, 0])
    poses[:, 1] = np.interp(s_frames, arclength, points[:, 1])
    poses[:, 2] = (np.interp(s_frames, arclength, unwrapped) + np.pi) % (2 * np.pi) - np.pi
    return poses


def _headings(points: np.ndarray) -> np.ndarray:
    d = np.gradient(points, axis=0)
    return np.arctan2(d[:, 1], d[:, 0])


def _driving_line(pitch_m: float, cfg: RouteConfig, cycles: int, step_m: float) -> np.ndarray:
    """``(K, 2)`` points every ~``step_m`` along the right-lane line of ``cycles`` route cycles."""
    nodes = np.array(list(ROUTE_CYCLE) * cycles + [ROUTE_CYCLE[0]], np.float64) * pitch_m
    directions = np.diff(nodes, axis=0)
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    right = np.stack([directions[:, 1], -directions[:, 0]], axis=1)
    # Corner k joins leg k-1 and leg k at node k; the lane lines are offset to the right.
    pieces: list[np.ndarray] = []
    current = nodes[0] + cfg.lane_offset_m * right[0]
    for k in range(1, len(directions)):
        d_in, d_out = directions[k - 1], directions[k]
        cross = d_in[0] * d_out[1] - d_in[1] * d_out[0]
        if abs(cross) < 1e-9:  # straight on through the intersection
            continue
        # Intersection of the two offset lines = node + offset * (right_in + right_out) for 90 deg.
        corner = nodes[k] + cfg.lane_offset_m * (right[k - 1] + right[k])
        radius = cfg.left_turn_radius_m if cross > 0 else cfg.right_turn_radius_m
        t_in = corner - radius * d_in
        t_out = corner + radius * d_out
        pieces.append(_segment(current, t_in, step_m))
        normal_in = np.array([-d_in[1], d_in[0]]) * (1.0 if cross > 0 else -1.0)  # towards the centre
        centre = t_in + radius * normal_in
        a0 = math.atan2(t_in[1] - centre[1], t_in[0] - centre[0])
        a1 = a0 + (math.pi / 2 if cross > 0 else -math.pi / 2)
        n_arc = max(2, int(math.ceil(radius * math.pi / 2 / step_m)))
        angles = np.linspace(a0, a1, n_arc + 1)[:-1]  # [t_in, t_out)
        pieces.append(centre + radius * np.stack([np.cos(angles), np.sin(angles)], axis=1))
        current = t_out
    pieces.append(_segment(current, nodes[-1] + cfg.lane_offset_m * right[-1], step_m))
    return np.concatenate(pieces, axis=0)


def _segment(a: np.ndarray, b: np.ndarray, step_m: float) -> np.ndarray:
    n = max(1, int(math.ceil(np.linalg.norm(b - a) / step_m)))
    t = np.arange(n)[:, None] / n
    return a + t * (b - a)
