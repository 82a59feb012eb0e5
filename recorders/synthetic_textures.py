"""Procedural textures of the synthetic street world: facades, side walls, the street tile and the sky.

Pure numpy + OpenCV drawing; every texture is a deterministic function of its spec (which carries its
own seed), so textures can be generated lazily, in any order, by any thread.

Conventions:

* Images are ``(H, W, 3)`` uint8 **RGB**.
* Facade textures are anchored at the ground: texture row ``H - 1`` is at height 0 m, row 0 at the
  texture's full height; column 0 is the left edge of the wall seen from the street. One texel is
  ``1 / px_per_m`` metres.
* The street tile covers one block pitch ``P`` centred on an intersection: texel ``(col, row)`` is the
  ground point ``(x, y) = (col / px_per_m - P / 2, row / px_per_m - P / 2)`` relative to the
  intersection (x east, y north). It is periodic with period ``P``.
* The sky panorama covers azimuth ``[0, 2 pi)`` left to right and elevation from
  :data:`SKY_MAX_ELEVATION_RAD` (row 0) down to the horizon (last row); it wraps in azimuth.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np

FacadeStyle = Literal["brick", "stucco", "concrete", "glass", "stone", "metal"]
FACADE_STYLES: tuple[FacadeStyle, ...] = ("brick", "stucco", "concrete", "glass", "stone")

SKY_MAX_ELEVATION_RAD = math.radians(60.0)

_PALETTES: dict[str, tuple[tuple[int, int, int], ...]] = {
    "brick": ((150, 70, 50), (170, 92, 62), (120, 58, 44), (185, 128, 96), (112, 80, 70), (160, 110, 80)),
    "stucco": ((228, 212, 182), (212, 172, 112), (222, 172, 160), (172, 192, 204), (232, 232, 226), (192, 206, 172), (236, 200, 140)),
    "concrete": ((152, 152, 146), (178, 172, 160), (124, 124, 120), (166, 160, 150)),
    "glass": ((62, 84, 104), (60, 98, 98), (108, 92, 74), (80, 90, 112)),
    "stone": ((194, 184, 162), (164, 154, 136), (206, 196, 176), (150, 144, 134)),
}
_SIGN_COLOURS = ((200, 30, 40), (30, 80, 170), (30, 130, 60), (230, 180, 20), (20, 20, 24), (120, 30, 120), (230, 110, 20), (240, 240, 236))
_ACCENT_COLOURS = ((40, 90, 60), (40, 60, 110), (110, 60, 40), (150, 40, 40), (60, 60, 64), (190, 180, 150))
_WORDS = (
    "CAFE", "BAKERY", "PHARMACY", "BOOKS", "PIZZA", "BANK", "MARKET", "DELI", "SUSHI", "FLOWERS",
    "SALON", "OPTICS", "SHOES", "TAILOR", "HOTEL", "BAR", "NOODLES", "TOYS", "HARDWARE", "LAUNDRY",
    "KEBAB", "BISTRO", "GALLERY", "PHONES", "BIKES", "DENTIST", "TICKETS", "BUTCHER", "WINE", "FRUIT",
)


@dataclass(frozen=True)
class FacadeSpec:
    """Parameters of one facade texture (cheap to draw at world creation; pixels come later).

    Attributes:
        texture_id: index in the world's texture bank.
        seed: seed of the pixel generator.
        style: wall material.
        side: a plain side/back wall (few windows) rather than a street facade.
        ground_floor_m: height of the ground floor (shops) in metres.
        floor_m: height of each upper floor in metres.
    """

    texture_id: int
    seed: int
    style: FacadeStyle
    side: bool
    ground_floor_m: float
    floor_m: float

    def height_for_floors(self, upper_floors: int) -> float:
        """Building height in metres for ``upper_floors`` floors above the ground floor (+ parapet)."""
        return self.ground_floor_m + upper_floors * self.floor_m + 0.7


def make_facade_spec(rng: np.random.Generator, texture_id: int, *, side: bool) -> FacadeSpec:
    """Draw the parameters of a facade texture from ``rng``."""
    style: FacadeStyle = FACADE_STYLES[int(rng.integers(len(FACADE_STYLES)))]
    if side:
        style = ("brick", "stucco", "concrete")[int(rng.integers(3))]
    return FacadeSpec(
        texture_id=texture_id,
        seed=int(rng.integers(2**31 - 1)),
        style=style,
        side=side,
        ground_floor_m=float(rng.uniform(3.8, 4.8)),
        floor_m=float(rng.uniform(3.0, 3.6)),
    )


# ---------------------------------------------------------------------------------------------
# Noise
# ---------------------------------------------------------------------------------------------


def periodic_noise(rng: np.random.Generator, height_px: int, width_px: int, *, scale_px: float, octaves: int = 3) -> np.ndarray:
    """Smooth random field, periodic in both axes, with zero mean and unit standard deviation.

    A sum of ``octaves`` layers of bicubically interpolated white noise on grids of cell size
    ``scale_px``, ``scale_px / 2``, ... (amplitudes 1, 1/2, ...). Each coarse grid is padded
    periodically before interpolation, so the field tiles seamlessly (to a fraction of a pixel).

    Returns:
        ``(height_px, width_px)`` float32.
    """
    import cv2

    if scale_px >= 12.0 and min(height_px, width_px) >= 64:
        # Smooth fields are synthesised at half resolution and enlarged once (4x fewer texels).
        hh, hw = (height_px + 1) // 2, (width_px + 1) // 2
        half = np.pad(periodic_noise(rng, hh, hw, scale_px=scale_px / 2.0, octaves=octaves), 2, mode="wrap")
        big = cv2.resize(half, (2 * (hw + 4), 2 * (hh + 4)), interpolation=cv2.INTER_LINEAR)
        return np.ascontiguousarray(big[4 : 4 + height_px, 4 : 4 + width_px])
    field = np.zeros((height_px, width_px), np.float32)
    amplitude, scale, pad = 1.0, float(scale_px), 2
    for _ in range(max(1, int(octaves))):
        ny, nx = max(2, int(round(height_px / scale))), max(2, int(round(width_px / scale)))
        cell_y, cell_x = height_px / ny, width_px / nx
        coarse = np.pad(rng.standard_normal((ny, nx)).astype(np.float32), pad, mode="wrap")
        size = (int(round((nx + 2 * pad) * cell_x)), int(round((ny + 2 * pad) * cell_y)))
        fine = cv2.resize(coarse, size, interpolation=cv2.INTER_CUBIC)
        oy, ox = int(round(pad * cell_y)), int(round(pad * cell_x))
        field += amplitude * fine[oy : oy + height_px, ox : ox + width_px]
        amplitude *= 0.5
        scale = max(scale / 2.0, 1.0)
    field -= field.mean()
    std = float(field.std())
    return field / (std if std > 0 else 1.0)


def _grain(rng: np.random.Generator, shape: tuple[int, int], amplitude: float) -> np.ndarray:
    """Per-texel white noise, float32, uniform in ``[-amplitude, amplitude]``."""
    return (rng.random(shape, dtype=np.float32) * (2 * amplitude) - amplitude).astype(np.float32)


def _to_uint8(image: np.ndarray) -> np.ndarray:
    """Saturate a float image to uint8 (clipping in place when it owns its data)."""
    image = np.asarray(image, dtype=np.float32)
    if image.flags.writeable and image.base is None:
        np.clip(image, 0, 255, out=image)
    else:
        image = np.clip(image, 0, 255)
    return image.astype(np.uint8)


def _jitter(rng: np.random.Generator, colour: tuple[int, int, int], amount: float) -> tuple[int, int, int]:
    scale = 1.0 + rng.uniform(-amount, amount)
    tint = rng.uniform(-amount, amount, size=3) * 60
    return tuple(int(np.clip(c * scale + t, 0, 255)) for c, t in zip(colour, tint))  # type: ignore[return-value]


# ---------------------------------------------------------------------------------------------
# Wall materials
# ---------------------------------------------------------------------------------------------


def _masonry(rng: np.random.Generator, height_px: int, width_px: int, unit_w_px: float, unit_h_px: float, variation: float, joint: float) -> np.ndarray:
    """Running-bond masonry: per-unit brightness offsets plus darker/lighter joints, ``(H, W)`` float32."""
    rows = np.arange(height_px, dtype=np.float32)[:, None]
    cols = np.arange(width_px, dtype=np.float32)[None, :]
    course = np.floor(rows / unit_h_px)
    shifted = cols + (course % 2) * (unit_w_px / 2)
    unit = np.floor(shifted / unit_w_px)
    n_courses = int(height_px / unit_h_px) + 2
    n_units = int(width_px / unit_w_px) + 3
    table = rng.normal(0.0, variation, size=(n_courses, n_units)).astype(np.float32)
    field = table[course.astype(np.int64).clip(0, n_courses - 1), unit.astype(np.int64).clip(0, n_units - 1)]
    in_joint = ((rows % unit_h_px) < 1.0) | ((shifted % unit_w_px) < 1.0)
    return np.where(in_joint, joint, field).astype(np.float32)


def _wall_base(rng: np.random.Generator, spec: FacadeSpec, height_px: int, width_px: int, px_per_m: float) -> np.ndarray:
    """The bare wall material (no openings), ``(H, W, 3)`` float32 RGB."""
    base = np.array(_jitter(rng, _PALETTES[spec.style][int(rng.integers(len(_PALETTES[spec.style])))], 0.08), dtype=np.float32)
    if spec.style == "brick":
        pattern = _masonry(rng, height_px, width_px, 0.25 * px_per_m, 0.085 * px_per_m, 14.0, 30.0)
    elif spec.style == "stone":
        pattern = _masonry(rng, height_px, width_px, rng.uniform(0.8, 1.3) * px_per_m, rng.uniform(0.4, 0.6) * px_per_m, 10.0, -35.0)
    elif spec.style == "concrete":
        pattern = _masonry(rng, height_px, width_px, rng.uniform(2.0, 3.5) * px_per_m, rng.uniform(1.2, 1.8) * px_per_m, 6.0, -40.0)
        pattern = np.where(np.arange(width_px)[None, :] % max(int(rng.uniform(2.0, 3.5) * px_per_m), 2) == 0, -40.0, pattern)
    elif spec.style == "glass":
        pattern = np.zeros((height_px, width_px), np.float32)
    else:  # stucco
        pattern = 4.0 * periodic_noise(rng, height_px, width_px, scale_px=0.5 * px_per_m)
    blotch_amplitude = 3.0 if spec.style == "glass" else 6.0
    blotches = blotch_amplitude * periodic_noise(rng, height_px, width_px, scale_px=4.0 * px_per_m)
    # Weathering: darker towards the ground, streaks below the windows come with the openings.
    dirt = np.linspace(0.0, -18.0, height_px, dtype=np.float32)[:, None]
    shade = pattern + blotches + dirt + _grain(rng, (height_px, width_px), 4.0)
    return base[None, None, :] + shade[:, :, None]


# ---------------------------------------------------------------------------------------------
# Openings: windows, shop fronts, doors, signs
# ---------------------------------------------------------------------------------------------


class _Canvas:
    """Drawing in metres on a ground-anchored texture (x from the left edge, z up from the ground)."""

    def __init__(self, image: np.ndarray, px_per_m: float):
        self.image = image
        self.ppm = px_per_m
        self.height_px = image.shape[0]

    def x(self, x_m: float) -> int:
        return int(round(x_m * self.ppm))

    def z(self, z_m: float) -> int:
        return int(round(self.height_px - 1 - z_m * self.ppm))

    def rect(self, x0_m: float, z0_m: float, x1_m: float, z1_m: float, colour, thickness: int = -1) -> None:
        cv2.rectangle(self.image, (self.x(x0_m), self.z(z1_m)), (self.x(x1_m), self.z(z0_m)), tuple(int(c) for c in colour), thickness)

    def line(self, x0_m: float, z0_m: float, x1_m: float, z1_m: float, colour, thickness_px: int) -> None:
        cv2.line(self.image, (self.x(x0_m), self.z(z0_m)), (self.x(x1_m), self.z(z1_m)), tuple(int(c) for c in colour), max(1, thickness_px))

    def gradient_rect(self, x0_m: float, z0_m: float, x1_m: float, z1_m: float, top, bottom) -> None:
        r0, r1 = self.z(z1_m), self.z(z0_m)
        c0, c1 = self.x(x0_m), self.x(x1_m)
        r0, r1 = max(r0, 0), min(r1, self.height_px - 1)
        c0, c1 = max(c0, 0), min(c1, self.image.shape[1] - 1)
        if r1 <= r0 or c1 <= c0:
            return
        t = np.linspace(0.0, 1.0, r1 - r0 + 1, dtype=np.float32)[:, None, None]
        ramp = np.asarray(top, np.float32) * (1 - t) + np.asarray(bottom, np.float32) * t
        self.image[r0 : r1 + 1, c0 : c1 + 1] = np.broadcast_to(ramp, (r1 - r0 + 1, c1 - c0 + 1, 3)).astype(np.uint8)

    def text(self, text: str, x_m: float, z_m: float, height_m: float, colour, max_width_m: float) -> None:
        """Text with its baseline at ``z_m``, starting at ``x_m``, scaled to fit ``max_width_m``."""
        font = cv2.FONT_HERSHEY_DUPLEX
        (w, h), _ = cv2.getTextSize(text, font, 1.0, 2)
        scale = min(height_m * self.ppm / max(h, 1), max_width_m * self.ppm / max(w, 1))
        thickness = max(1, int(round(scale * 1.6)))
        cv2.putText(self.image, text, (self.x(x_m), self.z(z_m)), font, scale, tuple(int(c) for c in colour), thickness, cv2.LINE_AA)


def _window(canvas: _Canvas, rng: np.random.Generator, x0: float, z0: float, w: float, h: float, frame_rgb, glass_rgb, mullion: str, wall_rgb) -> None:
    """One window: sill, glass with reflection gradient, curtains or lights, frame and mullions."""
    ppm = canvas.ppm
    frame_px = max(2, int(round(0.09 * ppm)))
    canvas.rect(x0 - 0.12, z0 - 0.14, x0 + w + 0.12, z0, tuple(min(255, c + 45) for c in wall_rgb))  # sill
    brightness = rng.uniform(-25, 30)
    top = np.clip(np.asarray(glass_rgb) + brightness + 40, 0, 255)
    bottom = np.clip(np.asarray(glass_rgb) + brightness - 10, 0, 255)
    canvas.gradient_rect(x0, z0, x0 + w, z0 + h, top, bottom)
    state = rng.random()
    if state < 0.25:  # curtains drawn on one or both sides
        curtain = _jitter(rng, ((232, 226, 210), (200, 180, 150), (170, 60, 60), (220, 220, 230))[int(rng.integers(4))], 0.05)
        frac = rng.uniform(0.25, 0.5)
        canvas.rect(x0, z0, x0 + w * frac, z0 + h, curtain)
        if rng.random() < 0.5:
            canvas.rect(x0 + w * (1 - frac), z0, x0 + w, z0 + h, curtain)
    elif state < 0.37:  # blinds half down
        blind = _jitter(rng, (220, 214, 196), 0.05)
        canvas.rect(x0, z0 + h * rng.uniform(0.3, 0.7), x0 + w, z0 + h, blind)
        for k in range(int(h / 0.12)):
            canvas.line(x0, z0 + h - k * 0.12, x0 + w, z0 + h - k * 0.12, tuple(c - 25 for c in blind), 1)
    elif state < 0.43:  # light on
        canvas.rect(x0, z0, x0 + w, z0 + h, _jitter(rng, (236, 204, 120), 0.06))
    elif state < 0.6:  # diagonal sky reflection
        pts = np.array(
            [
                (canvas.x(x0 + w * 0.15), canvas.z(z0 + h)),
                (canvas.x(x0 + w * 0.55), canvas.z(z0 + h)),
                (canvas.x(x0 + w * 0.25), canvas.z(z0)),
                (canvas.x(x0), canvas.z(z0)),
            ],
            np.int32,
        )
        cv2.fillConvexPoly(canvas.image, pts, tuple(int(c) for c in np.clip(top + 35, 0, 255)))
    canvas.rect(x0, z0, x0 + w, z0 + h, frame_rgb, frame_px)
    if mullion in ("cross", "vertical"):
        canvas.line(x0 + w / 2, z0, x0 + w / 2, z0 + h, frame_rgb, frame_px - 1)
    if mullion == "cross":
        canvas.line(x0, z0 + h * 0.68, x0 + w, z0 + h * 0.68, frame_rgb, frame_px - 1)


def _shopfront(canvas: _Canvas, rng: np.random.Generator, x0: float, x1: float, ground_floor_m: float, wall_rgb) -> None:
    """A shop unit between ``x0`` and ``x1`` metres: display window, door, sign band, maybe an awning."""
    width = x1 - x0
    sign_z0 = ground_floor_m - 1.05
    sign_rgb = _SIGN_COLOURS[int(rng.integers(len(_SIGN_COLOURS)))]
    text_rgb = (250, 250, 245) if sum(sign_rgb) < 450 else (25, 25, 30)
    canvas.rect(x0 + 0.15, sign_z0, x1 - 0.15, sign_z0 + 0.8, sign_rgb)
    canvas.rect(x0 + 0.15, sign_z0, x1 - 0.15, sign_z0 + 0.8, tuple(max(0, c - 60) for c in sign_rgb), 2)
    word = _WORDS[int(rng.integers(len(_WORDS)))]
    if rng.random() < 0.4:
        word = f"{word} {int(rng.integers(1, 99))}"
    canvas.text(word, x0 + 0.5, sign_z0 + 0.17, 0.5, text_rgb, width - 1.0)
    door_w = 1.1
    door_x = x0 + (0.4 if rng.random() < 0.5 else width - door_w - 0.4)
    glass_x0, glass_x1 = (door_x + door_w + 0.3, x1 - 0.35) if door_x < x0 + width / 2 else (x0 + 0.35, door_x - 0.3)
    frame_rgb = _ACCENT_COLOURS[int(rng.integers(len(_ACCENT_COLOURS)))]
    if glass_x1 - glass_x0 > 0.8:
        canvas.gradient_rect(glass_x0, 0.55, glass_x1, sign_z0 - 0.2, (120, 130, 140), (45, 48, 52))
        for _ in range(int(rng.integers(2, 6))):  # goods and shelves behind the glass
            gx = rng.uniform(glass_x0, glass_x1 - 0.4)
            gz = rng.uniform(0.6, sign_z0 - 0.9)
            canvas.rect(gx, gz, gx + rng.uniform(0.2, 0.7), gz + rng.uniform(0.2, 0.6), _jitter(rng, _SIGN_COLOURS[int(rng.integers(len(_SIGN_COLOURS)))], 0.2))
        n_panes = max(1, int((glass_x1 - glass_x0) / 1.6))
        for k in range(1, n_panes):
            xk = glass_x0 + k * (glass_x1 - glass_x0) / n_panes
            canvas.line(xk, 0.55, xk, sign_z0 - 0.2, frame_rgb, 3)
        canvas.rect(glass_x0, 0.55, glass_x1, sign_z0 - 0.2, frame_rgb, 3)
        canvas.rect(glass_x0 - 0.1, 0.0, glass_x1 + 0.1, 0.55, tuple(max(0, c - 30) for c in wall_rgb))
    canvas.gradient_rect(door_x, 0.0, door_x + door_w, 2.3, (90, 96, 104), (40, 42, 46))
    canvas.rect(door_x, 0.0, door_x + door_w, 2.3, frame_rgb, 4)
    canvas.line(door_x + door_w - 0.2, 1.0, door_x + door_w - 0.2, 1.25, (200, 200, 190), 2)
    if rng.random() < 0.35:  # striped awning
        stripe = _SIGN_COLOURS[int(rng.integers(len(_SIGN_COLOURS)))]
        za, zb = sign_z0 - 0.75, sign_z0 - 0.05
        canvas.rect(x0 + 0.2, za, x1 - 0.2, zb, (236, 232, 222))
        k = 0
        x = x0 + 0.2
        while x < x1 - 0.2:
            if k % 2 == 0:
                canvas.rect(x, za, min(x + 0.35, x1 - 0.2), zb, stripe)
            x += 0.35
            k += 1


def _entrance(canvas: _Canvas, rng: np.random.Generator, x0: float, x1: float, ground_floor_m: float, wall_rgb, frame_rgb) -> None:
    """A residential ground floor: a door with steps and a house number, small windows."""
    door_x = rng.uniform(x0 + 0.5, max(x0 + 0.6, x1 - 2.0))
    canvas.rect(door_x - 0.3, 0.0, door_x + 1.6, 0.3, (170, 168, 160))
    canvas.rect(door_x, 0.3, door_x + 1.3, 2.7, _ACCENT_COLOURS[int(rng.integers(len(_ACCENT_COLOURS)))])
    canvas.rect(door_x, 0.3, door_x + 1.3, 2.7, frame_rgb, 3)
    canvas.rect(door_x + 0.15, 1.6, door_x + 1.15, 2.5, (70, 80, 92))
    canvas.rect(door_x + 1.45, 2.0, door_x + 1.85, 2.35, (30, 60, 140))
    canvas.text(str(int(rng.integers(1, 200))), door_x + 1.48, 2.07, 0.22, (250, 250, 250), 0.34)
    x = x0 + 0.6
    while x + 1.2 < x1:
        if x + 1.2 < door_x - 0.3 or x > door_x + 1.9:
            _window(canvas, rng, x, 1.1, 1.0, 1.5, frame_rgb, (70, 82, 96), "vertical", wall_rgb)
        x += 2.2


def render_facade(spec: FacadeSpec, width_m: float, height_m: float, px_per_m: float) -> np.ndarray:
    """Draw the facade texture of ``spec``.

    Args:
        spec: the texture's parameters (its seed decides every random choice).
        width_m, height_m: size of the texture in metres.
        px_per_m: texels per metre.

    Returns:
        ``(round(height_m * px_per_m), round(width_m * px_per_m), 3)`` uint8 RGB, ground-anchored.
    """
    rng = np.random.default_rng(spec.seed)
    height_px, width_px = int(round(height_m * px_per_m)), int(round(width_m * px_per_m))
    if spec.style == "metal":
        return _painted_metal(rng, height_px, width_px, px_per_m)
    base = _wall_base(rng, spec, height_px, width_px, px_per_m)
    wall_rgb = tuple(int(c) for c in np.clip(base.reshape(-1, 3).mean(axis=0), 0, 255))
    canvas = _Canvas(_to_uint8(base), px_per_m)
    frame_rgb = ((236, 236, 230), (60, 56, 52), (120, 84, 52), (40, 60, 50), (170, 170, 176))[int(rng.integers(5))]
    glass_rgb = np.array(((70, 84, 100), (60, 74, 78), (84, 92, 110), (50, 60, 70))[int(rng.integers(4))])
    if spec.side:
        _side_openings(canvas, rng, spec, width_m, height_m, frame_rgb, glass_rgb, wall_rgb)
        return canvas.image
    window_w = rng.uniform(1.0, 1.7)
    window_h = min(spec.floor_m - 1.2, rng.uniform(1.4, 2.0))
    bay_m = max(window_w + 0.8, rng.uniform(2.2, 3.6))
    mullion = ("cross", "vertical", "none")[int(rng.integers(3))]
    balconies = spec.style in ("stucco", "concrete") and rng.random() < 0.5
    shutters = spec.style in ("stucco", "stone") and rng.random() < 0.45
    shutter_rgb = _ACCENT_COLOURS[int(rng.integers(len(_ACCENT_COLOURS)))]
    string_course = spec.style in ("brick", "stone", "stucco") and rng.random() < 0.6
    n_bays = max(1, int(width_m / bay_m))
    margin = (width_m - n_bays * bay_m) / 2
    if spec.style == "glass":
        _curtain_wall(canvas, rng, spec, width_m, height_m, glass_rgb)
    else:
        z_floor = spec.ground_floor_m
        while z_floor + spec.floor_m < height_m + 1e-6:
            if string_course:
                canvas.rect(0, z_floor - 0.12, width_m, z_floor + 0.12, tuple(min(255, c + 30) for c in wall_rgb))
            sill_z = z_floor + 0.95
            for b in range(n_bays):
                x0 = margin + b * bay_m + (bay_m - window_w) / 2
                if shutters:
                    canvas.rect(x0 - window_w / 2 - 0.05, sill_z, x0 - 0.05, sill_z + window_h, shutter_rgb)
                    canvas.rect(x0 + window_w + 0.05, sill_z, x0 + window_w * 1.5 + 0.05, sill_z + window_h, shutter_rgb)
                    for k in range(1, int(window_h / 0.15)):
                        zz = sill_z + k * 0.15
                        dark = tuple(max(0, c - 35) for c in shutter_rgb)
                        canvas.line(x0 - window_w / 2 - 0.05, zz, x0 - 0.05, zz, dark, 1)
                        canvas.line(x0 + window_w + 0.05, zz, x0 + window_w * 1.5 + 0.05, zz, dark, 1)
                _window(canvas, rng, x0, sill_z, window_w, window_h, frame_rgb, glass_rgb, mullion, wall_rgb)
                if balconies and rng.random() < 0.6:
                    canvas.rect(x0 - 0.3, z_floor, x0 + window_w + 0.3, z_floor + 0.15, (90, 90, 92))
                    canvas.line(x0 - 0.3, z_floor + 1.0, x0 + window_w + 0.3, z_floor + 1.0, (40, 40, 44), 3)
                    x = x0 - 0.3
                    while x <= x0 + window_w + 0.31:
                        canvas.line(x, z_floor + 0.15, x, z_floor + 1.0, (40, 40, 44), 2)
                        x += 0.15
            z_floor += spec.floor_m
    # Ground floor: shop units or a residential entrance.
    if rng.random() < 0.75:
        n_units = max(1, int(width_m / rng.uniform(5.0, 9.0)))
        edges = np.linspace(0.0, width_m, n_units + 1)
        for k in range(n_units):
            _shopfront(canvas, rng, float(edges[k]), float(edges[k + 1]), spec.ground_floor_m, wall_rgb)
    else:
        _entrance(canvas, rng, 0.0, width_m, spec.ground_floor_m, wall_rgb, frame_rgb)
    if rng.random() < 0.5:  # drainpipe
        x = rng.uniform(0.2, width_m - 0.2)
        canvas.line(x, 0.0, x, height_m, (84, 84, 86), max(2, int(0.08 * px_per_m)))
    return canvas.image


def pole_spec(texture_id: int, seed: int) -> FacadeSpec:
    """The texture of lamp posts: painted metal (see :func:`render_facade`)."""
    return FacadeSpec(texture_id=texture_id, seed=seed, style="metal", side=True, ground_floor_m=0.0, floor_m=1.0)


def _painted_metal(rng: np.random.Generator, height_px: int, width_px: int, px_per_m: float) -> np.ndarray:
    """Dark painted metal with faint vertical streaks, a plinth at the bottom and bands every 1.5 m."""
    base = np.array((52, 62, 58), np.float32)
    streaks = 5.0 * periodic_noise(rng, 8, width_px, scale_px=3.0)[:1]
    image = base[None, None, :] + (streaks + _grain(rng, (height_px, width_px), 3.0))[:, :, None]
    rows = np.arange(height_px)[::-1] / px_per_m  # height of each row in metres
    image[rows < 0.6] *= 0.75  # plinth
    image[(rows % 1.5) < 0.06] += 40.0  # reflective bands
    return _to_uint8(image)


def _curtain_wall(canvas: _Canvas, rng: np.random.Generator, spec: FacadeSpec, width_m: float, height_m: float, glass_rgb) -> None:
    """Glass curtain wall above the ground floor: panels with per-panel reflections, mullions, spandrels."""
    panel_w = rng.uniform(1.2, 1.8)
    mullion_rgb = ((180, 184, 190), (60, 62, 66), (140, 120, 90))[int(rng.integers(3))]
    z = spec.ground_floor_m
    sky = np.array((170, 190, 210), np.float32)
    while z + spec.floor_m < height_m + 1e-6:
        x = 0.0
        while x < width_m:
            mix = rng.uniform(0.0, 0.55)
            colour = np.clip(np.asarray(glass_rgb, np.float32) * (1 - mix) + sky * mix + rng.uniform(-12, 12), 0, 255)
            canvas.gradient_rect(x, z + 0.9, min(x + panel_w, width_m), z + spec.floor_m, colour + 25, colour - 15)
            canvas.line(x, z, x, z + spec.floor_m, mullion_rgb, 3)
            x += panel_w
        canvas.rect(0, z, width_m, z + 0.9, tuple(int(c) for c in np.asarray(glass_rgb) * 0.6))
        canvas.line(0, z + 0.9, width_m, z + 0.9, mullion_rgb, 3)
        z += spec.floor_m


def _side_openings(canvas: _Canvas, rng: np.random.Generator, spec: FacadeSpec, width_m: float, height_m: float, frame_rgb, glass_rgb, wall_rgb) -> None:
    """A side or back wall: sparse small windows, a service door, maybe a poster or a mural."""
    z = spec.ground_floor_m
    cols = np.sort(rng.uniform(0.8, width_m - 1.8, size=int(rng.integers(1, 4))))
    while z + spec.floor_m < height_m:
        for x in cols:
            if rng.random() < 0.7:
                _window(canvas, rng, float(x), z + 1.0, 0.9, 1.2, frame_rgb, glass_rgb, "none", wall_rgb)
        z += spec.floor_m
    door_x = rng.uniform(0.5, width_m - 2.0)
    canvas.rect(door_x, 0.0, door_x + 1.2, 2.2, (80, 84, 88))
    canvas.rect(door_x, 0.0, door_x + 1.2, 2.2, (50, 50, 52), 3)
    if rng.random() < 0.6:
        w = rng.uniform(2.5, min(6.0, width_m - 1.0))
        x0 = rng.uniform(0.3, width_m - w - 0.3)
        z0 = rng.uniform(2.8, 5.0)
        colour = _SIGN_COLOURS[int(rng.integers(len(_SIGN_COLOURS)))]
        canvas.rect(x0, z0, x0 + w, z0 + w * 0.6, colour)
        canvas.rect(x0 + 0.2, z0 + 0.2, x0 + w * 0.45, z0 + w * 0.6 - 0.2, _jitter(rng, (230, 220, 200), 0.1))
        text_rgb = (250, 250, 245) if sum(colour) < 450 else (25, 25, 30)
        canvas.text(_WORDS[int(rng.integers(len(_WORDS)))], x0 + w * 0.5, z0 + w * 0.25, w * 0.15, text_rgb, w * 0.47)


# ---------------------------------------------------------------------------------------------
# Street tile and sky
# ---------------------------------------------------------------------------------------------


def render_street_tile(seed: int, pitch_m: float, road_half_width_m: float, building_line_m: float, px_per_m: float) -> np.ndarray:
    """The periodic ground texture around one intersection (see the module docstring).

    Asphalt with repairs, centre dashes, stop lines and zebra crossings on the roads; kerbs; paving
    slabs on the sidewalks; manholes and drain grates.

    Returns:
        ``(S, S, 3)`` uint8 RGB with ``S = round(pitch_m * px_per_m)``.
    """
    rng = np.random.default_rng(seed)
    size = int(round(pitch_m * px_per_m))
    coords = (np.arange(size, dtype=np.float32) + 0.5) / px_per_m - pitch_m / 2
    ax, ay = np.abs(coords)[None, :], np.abs(coords)[:, None]
    on_road = (ax < road_half_width_m) | (ay < road_half_width_m)

    asphalt = 68.0 + 9.0 * periodic_noise(rng, size, size, scale_px=2.0 * px_per_m) + _grain(rng, (size, size), 9.0)
    patches = periodic_noise(rng, size, size, scale_px=6.0 * px_per_m)
    asphalt = asphalt - np.where(patches > 1.3, 12.0, 0.0) + np.where(patches < -1.6, 10.0, 0.0)
    # Paving slabs: 0.6 m squares with per-slab shade and dark joints.
    slab_m = 0.6
    sx = np.floor((coords + pitch_m / 2) / slab_m).astype(np.int64)
    n_slabs = int(pitch_m / slab_m) + 2
    slab_shade = rng.normal(0.0, 7.0, size=(n_slabs, n_slabs)).astype(np.float32)
    paving = 150.0 + slab_shade[sx[:, None].clip(0, n_slabs - 1), sx[None, :].clip(0, n_slabs - 1)] + _grain(rng, (size, size), 6.0)
    frac = ((coords + pitch_m / 2) % slab_m) * px_per_m
    joint = (frac < 1.2)[:, None] | (frac < 1.2)[None, :]
    paving = np.where(joint, paving - 45.0, paving)
    grey = np.where(on_road, asphalt, paving)
    image = np.repeat(grey[:, :, None], 3, axis=2)
    image[..., 2] += np.where(on_road, 3.0, -6.0)  # asphalt slightly blue, paving slightly warm
    image[..., 0] += np.where(on_road, 0.0, 6.0)
    image = _to_uint8(image)

    # Markings for one approach (the west arm, traffic on the right = south half), then rotated.
    marks = np.zeros((size, size), np.uint8)
    centre = size / 2

    def px(x_m: float) -> int:
        return int(round(centre + x_m * px_per_m))

    x = -(road_half_width_m + 7.0)
    while x > -pitch_m / 2:
        cv2.rectangle(marks, (px(x - 3.0), px(-0.08)), (px(x), px(0.08)), 255, -1)  # centre dashes
        x -= 8.0
    cv2.rectangle(marks, (px(-road_half_width_m - 4.3), px(-road_half_width_m + 0.3)), (px(-road_half_width_m - 3.9), px(0.0)), 255, -1)  # stop line
    z = -road_half_width_m + 0.4
    while z < road_half_width_m - 0.4:  # zebra crossing, bars along the road
        cv2.rectangle(marks, (px(-road_half_width_m - 3.4), px(z)), (px(-road_half_width_m - 0.6), px(z + 0.5)), 255, -1)
        z += 1.0
    marks = marks | np.rot90(marks, 1) | np.rot90(marks, 2) | np.rot90(marks, 3)
    wear = periodic_noise(rng, size, size, scale_px=0.3 * px_per_m)
    paint = (marks > 0) & (wear > -1.2)
    image[paint] = np.clip(np.array((222, 222, 212), np.float32) + 8.0 * wear[paint, None], 0, 255).astype(np.uint8)

    # Kerb stones along the sidewalks.
    kerb = ((np.abs(ax - road_half_width_m) < 0.15) & (ay > road_half_width_m)) | ((np.abs(ay - road_half_width_m) < 0.15) & (ax > road_half_width_m))
    image[kerb] = (188, 186, 178)
    # Manholes on the roads, drain grates at the kerbs.
    for _ in range(6):
        along = rng.uniform(road_half_width_m + 4.0, pitch_m / 2 - 2.0) * (1 if rng.random() < 0.5 else -1)
        across = rng.uniform(-road_half_width_m + 1.0, road_half_width_m - 1.0)
        cxy = (px(along), px(across)) if rng.random() < 0.5 else (px(across), px(along))
        cv2.circle(image, cxy, int(0.32 * px_per_m), (52, 52, 54), -1)
        cv2.circle(image, cxy, int(0.32 * px_per_m), (100, 100, 100), 2)
        cv2.circle(image, cxy, int(0.18 * px_per_m), (80, 80, 80), 1)
    for sign in (-1, 1):
        for axis in (0, 1):
            along = rng.uniform(road_half_width_m + 3.0, pitch_m / 2 - 3.0) * (1 if rng.random() < 0.5 else -1)
            c0 = (px(along - 0.3), px(sign * (road_half_width_m - 0.45)))
            c1 = (px(along + 0.3), px(sign * (road_half_width_m - 0.15)))
            if axis:
                c0, c1 = (c0[1], c0[0]), (c1[1], c1[0])
            cv2.rectangle(image, c0, c1, (40, 40, 42), -1)
            for k in range(5):
                t = along - 0.25 + k * 0.12
                a, b = (px(t), px(sign * (road_half_width_m - 0.42))), (px(t), px(sign * (road_half_width_m - 0.18)))
                if axis:
                    a, b = (a[1], a[0]), (b[1], b[0])
                cv2.line(image, a, b, (110, 110, 108), 1)
    return image


def render_sky(seed: int, width_px: int = 2048, height_px: int = 384) -> np.ndarray:
    """Sky panorama: blue gradient from the horizon up with soft, periodic clouds.

    Returns:
        ``(height_px, width_px, 3)`` uint8 RGB; see the module docstring for its axes.
    """
    rng = np.random.default_rng(seed)
    t = np.linspace(1.0, 0.0, height_px, dtype=np.float32)[:, None, None]  # 1 at the top row
    horizon = np.array((206, 218, 230), np.float32)
    zenith = np.array((96, 140, 204), np.float32)
    sky = horizon * (1 - t**0.7) + zenith * t**0.7
    cover = periodic_noise(rng, height_px, width_px, scale_px=160.0, octaves=4)
    cloud = np.clip((cover - 0.4) / 1.2, 0.0, 1.0)[:, :, None] * (0.25 + 0.75 * t)
    sky = sky * (1 - 0.8 * cloud) + np.array((244, 244, 246), np.float32) * 0.8 * cloud
    return _to_uint8(np.broadcast_to(sky, (height_px, width_px, 3)))
