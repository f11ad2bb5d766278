"""Embedded synthetic spacecraft benchmark: procedural spacecraft, rendered views, exact ground truth.

A synthetic stand-in for SpaceSense-Bench so the pipeline runs with no download.  Every view is
deterministic for ``(seed, spacecraft name, view index)``; the renderer's design is in docs/decisions.md.
"""

from __future__ import annotations

import dataclasses
import hashlib
import inspect
import math
from typing import Mapping, Sequence

import cv2
import numpy as np

from pipeline.params import PAPER

__all__ = ["PART_NAMES", "stable_hash", "make_spacecraft", "sample_view", "rasterize", "synthetic_plan",
           "sampling_options", "view_rng", "generate_view"]

PART_BACKGROUND, PART_BUS, PART_PANEL, PART_BOOM, PART_DISH, PART_PAYLOAD = range(6)
PART_NAMES = ("background", "bus", "panel", "antenna/boom/truss", "dish", "payload")

BACKGROUNDS = ("stars", "earth", "lab")
HARD_CASES = ("none", "glare", "flare", "underexposed", "noise", "blur")

# name: (albedo rgb, specular k_s, shininess, crinkle strength)
_MATERIALS = {
    "none": ((0.0, 0.0, 0.0), 0.0, 1.0, 0.0),
    "gold_foil": ((0.82, 0.60, 0.20), 0.85, 35.0, 0.45),
    "silver_foil": ((0.72, 0.72, 0.74), 0.80, 35.0, 0.40),
    "white": ((0.86, 0.86, 0.83), 0.12, 12.0, 0.0),
    "grey": ((0.42, 0.43, 0.46), 0.25, 20.0, 0.0),
    "dark": ((0.07, 0.07, 0.08), 0.35, 40.0, 0.0),
    "solar_cell": ((0.05, 0.08, 0.24), 0.75, 90.0, 0.0),
    "panel_back": ((0.70, 0.70, 0.68), 0.10, 10.0, 0.0),
    "cell_gap": ((0.55, 0.56, 0.60), 0.30, 20.0, 0.0),
    "metal": ((0.62, 0.62, 0.64), 0.55, 30.0, 0.0),
    "black": ((0.12, 0.12, 0.12), 0.20, 20.0, 0.0),
}
MATERIAL_NAMES = tuple(_MATERIALS)
_MAT = {n: i for i, n in enumerate(MATERIAL_NAMES)}
_MAT_ALBEDO, _MAT_KS, _MAT_SHIN, _MAT_CRINKLE = (np.array(col, np.float32) for col in zip(*_MATERIALS.values()))


def stable_hash(text: str) -> int:
    """Hash a string to 32 bits, the same in every process (unlike ``hash``).

    Parameters
    ----------
    text : str
        The string.

    Returns
    -------
    int
        The first 4 bytes of its sha256, little-endian.
    """
    return int.from_bytes(hashlib.sha256(text.encode()).digest()[:4], "little")


@dataclasses.dataclass
class SpacecraftModel:
    """Object-frame geometry of one spacecraft identity: convex faces (k, 3) and thick segments (S, 2, 3).

    ``seg_width`` is in object units, ``seg_max_px`` a width cap in px at 384; ``face_edge_mat`` is the
    material of a 1-px outline (cell gaps; -1 = none); ``face_jitter`` multiplies the albedo.
    """

    name: str
    faces: list
    face_normal: np.ndarray
    face_mat: np.ndarray
    face_back_mat: np.ndarray
    face_part: np.ndarray
    face_two_sided: np.ndarray
    face_edge_mat: np.ndarray
    face_jitter: np.ndarray
    segments: np.ndarray
    seg_width: np.ndarray
    seg_max_px: np.ndarray
    seg_mat: np.ndarray
    seg_part: np.ndarray

    @property
    def radius(self) -> float:
        pts = np.concatenate([np.concatenate(self.faces), self.segments.reshape(-1, 3)])
        return float(np.linalg.norm(pts, axis=1).max())


_DTYPES = {"face_normal": np.float64, "face_mat": np.int32, "face_back_mat": np.int32, "face_part": np.uint8,
           "face_two_sided": bool, "face_edge_mat": np.int32, "face_jitter": np.float32, "segments": np.float64,
           "seg_width": np.float64, "seg_max_px": np.float64, "seg_mat": np.int32, "seg_part": np.uint8}


class _Builder:
    def __init__(self, rng: np.random.Generator):
        self.rng = rng
        self.faces: list = []
        self.cols: dict[str, list] = {k: [] for k in _DTYPES}

    def _add(self, **values):
        for k, v in values.items():
            self.cols[k].append(v)

    def face(self, verts, normal, mat, part, *, two_sided=False, back=None, edge=None, jitter=0.08):
        self.faces.append(np.asarray(verts, np.float64))
        n = np.asarray(normal, np.float64)
        self._add(face_normal=n / (np.linalg.norm(n) + 1e-12), face_mat=_MAT[mat],
                  face_back_mat=_MAT[back] if back else _MAT[mat], face_part=part, face_two_sided=two_sided,
                  face_edge_mat=_MAT[edge] if edge else -1, face_jitter=1.0 + self.rng.uniform(-jitter, jitter))

    def segment(self, p0, p1, width, max_px, mat, part):
        self._add(segments=np.array([p0, p1], np.float64), seg_width=width, seg_max_px=max_px, seg_mat=_MAT[mat],
                  seg_part=part)

    def box(self, center, axes, half, mats, part):
        """Add a closed box: ``axes`` orthonormal rows, ``half`` half-sizes, ``mats`` 6 materials (+x..-z)."""
        c = np.asarray(center, float)
        ax = np.asarray(axes, float)
        for k, (i, s) in enumerate([(0, 1), (0, -1), (1, 1), (1, -1), (2, 1), (2, -1)]):
            j, l = [a for a in range(3) if a != i]
            fc = c + s * half[i] * ax[i]
            u, v = half[j] * ax[j], half[l] * ax[l]
            self.face([fc - u - v, fc + u - v, fc + u + v, fc - u + v], s * ax[i], mats[k], part)

    def prism(self, center, axes, radius, half_h, n, side_mat, cap_mat, part):
        """Add a closed regular n-gon prism along ``axes[2]`` (n >= 12 reads as a cylinder)."""
        c = np.asarray(center, float)
        ex, ey, ez = np.asarray(axes, float)
        ang = np.arange(n) * 2 * np.pi / n + self.rng.uniform(0, 2 * np.pi / n)
        ring = np.cos(ang)[:, None] * ex + np.sin(ang)[:, None] * ey
        top, bot = c + half_h * ez + radius * ring, c - half_h * ez + radius * ring
        for i in range(n):
            j = (i + 1) % n
            mid = 0.5 * (ring[i] + ring[j])
            self.face([bot[i], bot[j], top[j], top[i]], mid, side_mat, part, jitter=0.12)
        self.face(top, ez, cap_mat, part)
        self.face(bot[::-1], -ez, cap_mat, part)

    def panel(self, center, u, v, half_u, half_v, cols, rows, part=PART_PANEL,
              mat="solar_cell", back="panel_back"):
        """Two-sided flat panel split into cols x rows cells (cell grid; also keeps painter order local)."""
        c = np.asarray(center, float)
        u, v = np.asarray(u, float), np.asarray(v, float)
        n = np.cross(u, v)
        for a in range(cols):
            for b in range(rows):
                u0, u1 = -half_u + 2 * half_u * a / cols, -half_u + 2 * half_u * (a + 1) / cols
                v0, v1 = -half_v + 2 * half_v * b / rows, -half_v + 2 * half_v * (b + 1) / rows
                q = [c + u0 * u + v0 * v, c + u1 * u + v0 * v, c + u1 * u + v1 * v, c + u0 * u + v1 * v]
                self.face(q, n, mat, part, two_sided=True, back=back, edge="cell_gap", jitter=0.06)

    def dish(self, center, axis, radius, depth, mat, n=16):
        """Concave dish opening along ``axis``: a fan of n triangles (faceted paraboloid) + feed and struts."""
        c = np.asarray(center, float)
        ez = np.asarray(axis, float) / np.linalg.norm(axis)
        ex = _perpendicular(ez)
        ey = np.cross(ez, ex)
        ang = np.arange(n) * 2 * np.pi / n
        rim = c + depth * ez + radius * (np.cos(ang)[:, None] * ex + np.sin(ang)[:, None] * ey)
        for i in range(n):
            j = (i + 1) % n
            nrm = np.cross(rim[i] - c, rim[j] - c)
            if nrm @ ez < 0:
                nrm = -nrm
            self.face([c, rim[i], rim[j]], nrm, mat, PART_DISH, two_sided=True, jitter=0.03)
        tip = c + ez * (depth + 0.75 * radius)
        self.segment(c, tip, 0.03 * radius, 2, "metal", PART_DISH)
        for k in range(3):
            self.segment(rim[(k * n) // 3], tip, 0.01, 1, "metal", PART_DISH)

    def build(self, name: str) -> SpacecraftModel:
        arrays = {k: np.array(v, _DTYPES[k]) for k, v in self.cols.items()}
        arrays["segments"] = arrays["segments"].reshape(-1, 2, 3)
        return SpacecraftModel(name=name, faces=self.faces, **arrays)


def _perpendicular(v: np.ndarray) -> np.ndarray:
    a = np.array([1.0, 0, 0]) if abs(v[0]) < 0.9 else np.array([0, 1.0, 0])
    p = np.cross(v, a)
    return p / np.linalg.norm(p)


def _random_unit(rng: np.random.Generator) -> np.ndarray:
    v = rng.standard_normal(3)
    return v / np.linalg.norm(v)


def _surface_point(kind: str, dims: tuple, direction: np.ndarray) -> np.ndarray:
    """Point where a ray from the bus centre along ``direction`` leaves the bus."""
    d = direction / np.linalg.norm(direction)
    if kind == "box":
        t = min(dims[i] / abs(d[i]) for i in range(3) if abs(d[i]) > 1e-9)
    else:  # cylinder / prism with circumradius r, half height h (inscribed radius for safety)
        r, h = dims
        rxy = math.hypot(d[0], d[1])
        t = min(r / rxy if rxy > 1e-9 else np.inf, h / abs(d[2]) if abs(d[2]) > 1e-9 else np.inf)
    return d * t


def make_spacecraft(name: str, seed: int) -> SpacecraftModel:
    """Build the procedural spacecraft identity fixed by ``(seed, name)``.

    Bus, solar wings, booms, dishes and payloads, each part labelled (:data:`PART_NAMES`).

    Parameters
    ----------
    name : str
        The spacecraft's name (``syn-<group>-<i>``), one identity each.
    seed : int
        ``data.seed``.

    Returns
    -------
    SpacecraftModel
        Its object-frame geometry: convex faces and thick segments with materials and part labels.
    """
    rng = np.random.default_rng([int(seed), stable_hash(name)])
    b = _Builder(rng)
    eye = np.eye(3)

    # --- bus -----------------------------------------------------------------------------------
    kind = str(rng.choice(["box", "cylinder", "prism"], p=[0.45, 0.3, 0.25]))
    primary = str(rng.choice(["gold_foil", "silver_foil", "white", "grey", "dark"], p=[0.4, 0.1, 0.2, 0.15, 0.15]))
    secondary = str(rng.choice(["white", "grey", "gold_foil", "dark"]))
    if kind == "box":
        half = rng.uniform(0.45, 1.05, 3)
        dims: tuple = tuple(half)
        mats = [primary if rng.random() < 0.75 else secondary for _ in range(6)]
        b.box((0, 0, 0), eye, half, mats, PART_BUS)
        r_xy = float(max(half[0], half[1]))
        half_h = float(half[2])
    else:
        r_xy = float(rng.uniform(0.5, 1.0))
        half_h = float(rng.uniform(0.45, 1.3))
        n = 16 if kind == "cylinder" else int(rng.choice([5, 6, 8]))
        dims = (r_xy * math.cos(math.pi / n), half_h)
        b.prism((0, 0, 0), eye, r_xy, half_h, n, primary, secondary, PART_BUS)

    def random_mount() -> tuple[np.ndarray, np.ndarray]:
        """Draw a random unit direction and the point where it leaves the bus."""
        d = _random_unit(rng)
        return d, _surface_point(kind, dims, d)

    # --- solar wings ---------------------------------------------------------------------------
    n_wings = int(rng.choice([0, 1, 2, 3, 4], p=[0.08, 0.12, 0.5, 0.1, 0.2]))
    if n_wings:
        phase = rng.uniform(0, 2 * np.pi) if n_wings != 2 else rng.choice([0.0, np.pi / 2])
        if n_wings == 4 and rng.random() < 0.5:  # X layout
            spread = rng.uniform(0.3, 0.6)
            angles = [phase + s for s in (spread, -spread, np.pi + spread, np.pi - spread)]
        else:
            angles = [phase + k * 2 * np.pi / n_wings for k in range(n_wings)]
        n_panels = int(rng.integers(1, 5))
        pw, ph = rng.uniform(0.6, 1.4), rng.uniform(0.5, 1.2)
        cols, rows = int(rng.integers(2, 5)), int(rng.integers(2, 5))
        yoke = rng.uniform(0.15, 0.8)
        tilt = rng.uniform(0, np.pi)
        z_mount = rng.uniform(-0.5, 0.5) * half_h
        cell_mat = str(rng.choice(["solar_cell", "dark"], p=[0.8, 0.2]))
        for a in angles:
            d = np.array([math.cos(a), math.sin(a), 0.0])
            root = _surface_point(kind, dims, d) * np.array([1, 1, 0]) + np.array([0, 0, z_mount])
            start = root + d * yoke
            b.segment(root, start, 0.05, 2, "metal", PART_BOOM)
            up = math.cos(tilt) * eye[2] + math.sin(tilt) * np.cross(d, eye[2])
            for k in range(n_panels):
                c = start + d * (pw * (k + 0.5) + 0.04 * k)
                b.panel(c, d, up, pw / 2, ph / 2, cols, rows, mat=cell_mat)

    # --- booms, whip antennas, trusses ---------------------------------------------------------
    for _ in range(int(rng.choice([0, 1, 2, 3], p=[0.3, 0.35, 0.25, 0.1]))):
        d, root = random_mount()
        tip = root + d * rng.uniform(1.2, 3.5)
        b.segment(root, tip, 0.04, float(rng.choice([1, 2])), str(rng.choice(["metal", "black"])), PART_BOOM)
        if rng.random() < 0.5:  # magnetometer / sensor at the tip
            s = rng.uniform(0.05, 0.12)
            b.box(tip, eye, (s, s, s), ["grey"] * 6, PART_BOOM)
    for _ in range(int(rng.integers(0, 5))):
        d, root = random_mount()
        b.segment(root, root + d * rng.uniform(0.3, 1.3), 0.01, 1, "metal", PART_BOOM)
    if rng.random() < 0.35:
        d, root = random_mount()
        length = rng.uniform(1.5, 3.0)
        e1 = _perpendicular(d)
        e2 = np.cross(d, e1)
        w = rng.uniform(0.12, 0.25)
        rails = [root + w * (math.cos(t) * e1 + math.sin(t) * e2) for t in (0, 2.1, 4.2)]
        n_bays = max(2, int(length / 0.3))
        mat = str(rng.choice(["metal", "black", "gold_foil"]))
        for r0 in rails:
            b.segment(r0, r0 + d * length, 0.01, 1, mat, PART_BOOM)
        for k in range(n_bays):
            for i in range(3):
                p0 = rails[i] + d * (length * k / n_bays)
                p1 = rails[(i + 1) % 3] + d * (length * (k + 1) / n_bays)
                b.segment(p0, p1, 0.005, 1, mat, PART_BOOM)
        if rng.random() < 0.5:
            s = rng.uniform(0.15, 0.3)
            b.box(root + d * (length + s), eye, (s, s, s), [primary] * 6, PART_PAYLOAD)

    # --- dishes ----------------------------------------------------------------------------------
    for _ in range(int(rng.choice([0, 1, 2], p=[0.35, 0.5, 0.15]))):
        d, root = random_mount()
        base = root + d * rng.uniform(0.15, 0.7)
        b.segment(root, base, 0.05, 2, "metal", PART_BOOM)
        axis = d + 0.8 * _random_unit(rng)
        radius = rng.uniform(0.3, 0.95)
        b.dish(base, axis, radius, 0.3 * radius, str(rng.choice(["white", "grey", "gold_foil"], p=[0.6, 0.25, 0.15])))

    # --- payload boxes / instruments ------------------------------------------------------------
    for _ in range(int(rng.choice([0, 1, 2, 3], p=[0.2, 0.35, 0.3, 0.15]))):
        d, c = random_mount()
        s = rng.uniform(0.12, 0.4, 3)
        mat = str(rng.choice(["dark", "grey", "gold_foil", "white", "silver_foil"]))
        if rng.random() < 0.7:
            b.box(c + d * s.min() * 0.8, eye, s, [mat] * 6, PART_PAYLOAD)
        else:  # cylindrical instrument (telescope) along the mount direction
            ex = _perpendicular(d)
            b.prism(c + d * s[0], np.stack([ex, np.cross(d, ex), d]), s[1], s[0], 12, mat, "black", PART_PAYLOAD)
    return b.build(name)


@dataclasses.dataclass
class ViewSpec:
    rotation: np.ndarray          # (3, 3) object -> camera rotation
    sun: np.ndarray               # unit vector towards the sun, camera frame (camera looks along +z)
    hull_fraction: float          # target fraction of the frame covered by the projected convex hull
    fov_deg: float
    background: str
    hard_case: str


def random_rotation(rng: np.random.Generator) -> np.ndarray:
    """Uniform random rotation (Shoemake's quaternion method)."""
    u1, u2, u3 = rng.random(3)
    q = np.array([math.sqrt(1 - u1) * math.sin(2 * math.pi * u2), math.sqrt(1 - u1) * math.cos(2 * math.pi * u2),
                  math.sqrt(u1) * math.sin(2 * math.pi * u3), math.sqrt(u1) * math.cos(2 * math.pi * u3)])
    x, y, z, w = q
    return np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                     [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                     [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])


def sample_view(rng: np.random.Generator, *, tiny_range: Sequence[float] = PAPER.data.synthetic.tiny_range,
                regular_range: Sequence[float] = PAPER.data.synthetic.regular_range,
                tiny_probability: float = PAPER.data.synthetic.tiny_probability,
                hard_case_probability: float = PAPER.data.synthetic.hard_case_probability,
                background_weights: Sequence[float] = PAPER.data.synthetic.background_weights) -> ViewSpec:
    """Draw a view: rotation, sun, apparent size, background, hard case.

    Apparent size (the projected solid parts' convex hull over the frame) is log-uniform in ``tiny_range``
    with probability ``tiny_probability`` (approach shots), else in ``regular_range``.  The keywords' defaults
    are the ``data.synthetic`` params of the same names.

    Parameters
    ----------
    rng : numpy.random.Generator
        The view's generator (:func:`view_rng`).
    tiny_range : sequence of float
        ``(low, high)`` hull fraction of a tiny view (``data.synthetic.tiny_range``).
    regular_range : sequence of float
        ``(low, high)`` hull fraction of a regular view (``data.synthetic.regular_range``).
    tiny_probability : float
        Probability of a tiny view (``data.synthetic.tiny_probability``).
    hard_case_probability : float
        Probability of a hard case (glare, flare, underexposure, noise, blur;
        ``data.synthetic.hard_case_probability``).
    background_weights : sequence of float
        Relative weights of the stars, earth-limb and dark-lab backgrounds
        (``data.synthetic.background_weights``).

    Returns
    -------
    ViewSpec
        Rotation, sun direction, hull fraction, field of view, background and hard case.
    """
    a, b = tiny_range if rng.random() < tiny_probability else regular_range
    frac = math.exp(rng.uniform(math.log(float(a)), math.log(float(b))))
    sun = rng.standard_normal(3)
    sun[2] = -abs(sun[2]) * 1.2 + 0.35 * rng.random()  # mostly lit from the camera side, some backlit
    sun /= np.linalg.norm(sun)
    w = np.asarray(background_weights, float)
    background = str(rng.choice(BACKGROUNDS, p=w / w.sum()))
    hard = "none" if rng.random() >= hard_case_probability else str(rng.choice(HARD_CASES[1:]))
    return ViewSpec(rotation=random_rotation(rng), sun=sun, hull_fraction=frac,
                    fov_deg=float(rng.uniform(28, 50)), background=background, hard_case=hard)


_SHIFT = 4
_ONE = 1 << _SHIFT


class _CvRaster:
    name = "cv2"

    @staticmethod
    def fill(buf, pts, value):
        cv2.fillConvexPoly(buf, np.round(pts * _ONE).astype(np.int32), int(value), cv2.LINE_8, _SHIFT)

    @staticmethod
    def outline(buf, pts, value):
        cv2.polylines(buf, [np.round(pts * _ONE).astype(np.int32)], True, int(value), 1, cv2.LINE_8, _SHIFT)

    @staticmethod
    def line(buf, p0, p1, value, thickness):
        a, b = (tuple(int(v) for v in np.round(np.asarray(p) * _ONE)) for p in (p0, p1))
        cv2.line(buf, a, b, int(value), int(thickness), cv2.LINE_8, _SHIFT)


class _NumpyRaster:
    """Plain baseline: per-pixel inside tests over each primitive's bounding box."""

    name = "numpy"

    @staticmethod
    def _grid(buf, lo, hi):
        h, w = buf.shape
        x0, y0 = max(int(math.floor(lo[0])), 0), max(int(math.floor(lo[1])), 0)
        x1, y1 = min(int(math.ceil(hi[0])) + 1, w), min(int(math.ceil(hi[1])) + 1, h)
        if x0 >= x1 or y0 >= y1:
            return None
        ys, xs = np.mgrid[y0:y1, x0:x1]
        return (slice(y0, y1), slice(x0, x1)), xs.astype(np.float64), ys.astype(np.float64)

    @classmethod
    def fill(cls, buf, pts, value):
        g = cls._grid(buf, pts.min(0), pts.max(0))
        if g is None:
            return
        sl, xs, ys = g
        inside_pos, inside_neg = np.ones(xs.shape, bool), np.ones(xs.shape, bool)
        for i in range(len(pts)):
            (ax, ay), (bx, by) = pts[i], pts[(i + 1) % len(pts)]
            cross = (bx - ax) * (ys - ay) - (by - ay) * (xs - ax)
            inside_pos &= cross >= -1e-9
            inside_neg &= cross <= 1e-9
        buf[sl][inside_pos | inside_neg] = value

    @classmethod
    def line(cls, buf, p0, p1, value, thickness):
        p0, p1 = np.asarray(p0, float), np.asarray(p1, float)
        r = max(thickness / 2.0, 0.5)
        g = cls._grid(buf, np.minimum(p0, p1) - r, np.maximum(p0, p1) + r)
        if g is None:
            return
        sl, xs, ys = g
        d = p1 - p0
        L2 = float(d @ d) or 1e-12
        t = np.clip(((xs - p0[0]) * d[0] + (ys - p0[1]) * d[1]) / L2, 0, 1)
        dist = np.hypot(xs - p0[0] - t * d[0], ys - p0[1] - t * d[1])
        buf[sl][dist <= r + 1e-9] = value

    @classmethod
    def outline(cls, buf, pts, value):
        for i in range(len(pts)):
            cls.line(buf, pts[i], pts[(i + 1) % len(pts)], value, 1)


RASTERIZERS = {"cv2": _CvRaster, "numpy": _NumpyRaster}


@dataclasses.dataclass
class SyntheticView:
    image: np.ndarray     # uint8 [H, W, 3] RGB
    mask: np.ndarray      # bool [H, W] ground-truth foreground
    parts: np.ndarray     # uint8 [H, W] part labels (PART_NAMES)
    spacecraft: str
    background: str
    hard_case: str
    area_fraction: float  # mask.mean()


def _smooth_noise(rng, h, w, cells: Sequence[int], amps: Sequence[float] | None = None) -> np.ndarray:
    """Sum of bicubic-upsampled Gaussian grids (cheap fractal noise), float32 [h, w]."""
    out = np.zeros((h, w), np.float32)
    amps = amps or [0.5 ** i for i in range(len(cells))]
    for c, a in zip(cells, amps):
        g = rng.standard_normal((c + 3, c + 3)).astype(np.float32)
        up = cv2.resize(g, (w + 3 * w // c, h + 3 * h // c), interpolation=cv2.INTER_CUBIC)
        out += a * up[:h, :w]
    return out


def _smoothstep(x, lo, hi):
    t = np.clip((x - lo) / (hi - lo), 0, 1)
    return t * t * (3 - 2 * t)


def render_background(kind: str, rng: np.random.Generator, size: int, sun: np.ndarray) -> np.ndarray:
    """Background radiance, float32 [size, size, 3] in [0, ~1]: stars | earth | lab."""
    s = size / 384.0
    if kind != "stars" and size >= 64:  # smooth: half resolution, upsampled
        half = _background_smooth(kind, rng, (size + 1) // 2, sun, s)
        return cv2.resize(half, (size, size), interpolation=cv2.INTER_LINEAR)
    if kind != "stars":
        return _background_smooth(kind, rng, size, sun, s)
    img = np.full((size, size, 3), 0.004, np.float32)
    n = int(rng.integers(60, 500) * s * s) + 5
    ys, xs = rng.integers(0, size, n), rng.integers(0, size, n)
    mag = np.minimum(0.04 + 0.5 * rng.pareto(2.2, n), 1.0).astype(np.float32)
    tint = 1.0 + 0.15 * rng.standard_normal((n, 3)).astype(np.float32)
    img[ys, xs] = mag[:, None] * tint
    return np.clip(img, 0, 1)


def _background_smooth(kind: str, rng: np.random.Generator, size: int, sun: np.ndarray, s: float) -> np.ndarray:
    """Earth limb or dark lab at ``size`` px; ``s`` = output scale relative to 384 (for blur widths)."""
    h = w = size
    if kind == "earth":
        yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
        r_e = rng.uniform(0.9, 4.0) * size
        ang = rng.uniform(0, 2 * np.pi)
        depth = rng.uniform(0.15, 0.8) * size          # how far the limb reaches into the frame
        cx = size / 2 + math.cos(ang) * (r_e + size / 2 - depth)
        cy = size / 2 + math.sin(ang) * (r_e + size / 2 - depth)
        rr = np.sqrt((xx - cx) ** 2 + (yy - cy) ** 2) / r_e
        inside = rr < 1.0
        nz = -np.sqrt(np.clip(1 - rr ** 2, 0, 1))
        nx, ny = (xx - cx) / r_e, (yy - cy) / r_e
        day = np.clip(nx * sun[0] + ny * sun[1] + nz * sun[2], 0, 1) * 0.9 + 0.04
        land = _smoothstep(_smooth_noise(rng, h, w, [3, 7, 15, 31]), 0.35, 0.6)
        cloud = _smoothstep(_smooth_noise(rng, h, w, [6, 13, 27, 55, 110], [0.5, 0.45, 0.35, 0.25, 0.15]), 0.1, 0.7)
        ocean = np.array([0.03, 0.10, 0.30], np.float32)
        ground = np.array([0.20, 0.22, 0.10], np.float32)
        surf = ocean * (1 - land[..., None]) + ground * land[..., None]
        surf = surf * (1 - cloud[..., None]) + 0.9 * cloud[..., None]
        img = np.where(inside[..., None], surf * day[..., None], 0.0).astype(np.float32)
        hgt = 0.012 + 0.01 * rng.random()
        glow = np.exp(-np.abs(rr - 1.0) / hgt) * (0.15 + 0.5 * np.clip(nx * sun[0] + ny * sun[1], 0, 1))
        img += glow[..., None].astype(np.float32) * np.array([0.35, 0.55, 1.0], np.float32)
        return np.clip(img, 0, 1)
    # dark laboratory: dim gradient, faint blurred structures, vignette
    base = rng.uniform(0.01, 0.05)
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32) / size
    g = base * (1 + 0.8 * (yy if rng.random() < 0.5 else xx))
    img = np.repeat(g[..., None], 3, 2).astype(np.float32)
    layer = np.zeros((h, w), np.float32)
    for _ in range(int(rng.integers(1, 5))):
        x0, y0 = rng.integers(0, w), rng.integers(0, h)
        corner = (int(x0 + rng.integers(w // 8, w // 2)), int(y0 + rng.integers(h // 16, h // 3)))
        cv2.rectangle(layer, (int(x0), int(y0)), corner, float(rng.uniform(0.02, 0.08)), -1)
    layer = cv2.GaussianBlur(layer, (0, 0), 1.5 * s + 0.5)
    img += layer[..., None] * np.array([1.0, 0.97, 0.92], np.float32)
    img += 0.01 * _smooth_noise(rng, h, w, [8, 24])[..., None]
    vig = 1 - 0.5 * ((xx - 0.5) ** 2 + (yy - 0.5) ** 2)
    return np.clip(img * vig[..., None], 0, 1)


def _project(q: np.ndarray, f: float, c: float) -> np.ndarray:
    return f * q[:, :2] / q[:, 2:3] + c


@dataclasses.dataclass
class Rasterized:
    """Record-id buffer of one view and the per-record shading attributes (record 0 = background)."""

    ids: np.ndarray       # int32 [H, W]
    albedo: np.ndarray    # float32 [R, 3]
    normal: np.ndarray    # float32 [R, 3] camera frame
    material: np.ndarray  # int32 [R]
    part: np.ndarray      # uint8 [R]
    focal: float
    centre: float


def rasterize(model: SpacecraftModel, spec: ViewSpec, size: int, rng: np.random.Generator,
              rasterizer: str = "cv2") -> Rasterized:
    """Rasterise a view: camera distance and placement, then all primitives far-to-near into a record-id buffer.

    Parameters
    ----------
    model : SpacecraftModel
        The spacecraft.
    spec : ViewSpec
        The view (:func:`sample_view`).
    size : int
        The image side in pixels.
    rng : numpy.random.Generator
        The view's generator (image-plane placement).
    rasterizer : str
        ``cv2`` or ``numpy`` (:data:`RASTERIZERS`; a baseline differing only in which boundary pixels count).

    Returns
    -------
    Rasterized
        The record-id buffer [size, size] (0 = background) and each record's shading attributes.
    """
    rast = RASTERIZERS[rasterizer]
    R = spec.rotation
    f = (size / 2) / math.tan(math.radians(spec.fov_deg) / 2)
    c = (size - 1) / 2
    face_sizes = [len(v) for v in model.faces]
    pts_obj = np.concatenate([np.concatenate(model.faces), model.segments.reshape(-1, 3)])
    pc = pts_obj @ R.T
    radius = model.radius

    # distance so the projected hull covers the target fraction (projected size ~ 1/z)
    z_min = 1.3 * radius
    z = max(f * radius / (size * math.sqrt(spec.hull_fraction)), z_min)
    body = pc[:sum(face_sizes)] if face_sizes else pc  # size by the solid parts; booms may stick out
    for _ in range(3):
        q = body + np.array([0, 0, z])
        frac = float(cv2.contourArea(cv2.convexHull(_project(q, f, c).astype(np.float32)))) / (size * size)
        z = max(z * math.sqrt(frac / spec.hull_fraction), z_min)
    # placement: keep the projected bounding box inside the frame when it fits
    q = pc + np.array([0, 0, z])
    uv = _project(q, f, c)
    lo, hi = uv.min(0), uv.max(0)
    shift = np.zeros(2)
    for k in range(2):
        ext = hi[k] - lo[k]
        if ext <= size - 3:
            shift[k] = rng.uniform(1 - lo[k], size - 2 - hi[k])
        else:
            shift[k] = (c - 0.5 * (lo[k] + hi[k])) + rng.uniform(-0.15, 0.15) * (ext - size)
    q = pc + np.array([shift[0] * z / f, shift[1] * z / f, z])
    uv = _project(q, f, c)

    # --- primitives, sorted far to near -------------------------------------------------------
    n_face_pts = sum(face_sizes)
    starts = np.concatenate([[0], np.cumsum(face_sizes)])
    normals = model.face_normal @ R.T
    scale384 = size / 384.0
    prims = []  # (distance, kind, index, payload)
    records = [(np.zeros(3), np.zeros(3), 0, 0)]  # (albedo, normal, material, part); record 0 = background

    def record(*rec) -> int:
        records.append(rec)
        return len(records) - 1

    for i in range(len(model.faces)):
        qv = q[starts[i]:starts[i + 1]]
        cen = qv.mean(0)
        n = normals[i]
        back_facing = float(n @ cen) > 0
        if back_facing and not model.face_two_sided[i]:
            continue
        payload = (model.face_back_mat[i], -n) if back_facing else (model.face_mat[i], n)
        prims.append((float(np.linalg.norm(cen)), 0, i, payload))
    seg_q = q[n_face_pts:].reshape(-1, 2, 3)
    seg_uv = uv[n_face_pts:].reshape(-1, 2, 2)
    for j in range(len(seg_q)):
        a, b = seg_q[j]
        px_len = float(np.linalg.norm(seg_uv[j, 1] - seg_uv[j, 0]))
        pieces = int(min(8, max(1, px_len // 24)))
        for k in range(pieces):
            t0, t1 = k / pieces, (k + 1) / pieces
            mid = a + (b - a) * (t0 + t1) / 2
            prims.append((float(np.linalg.norm(mid)) - 1e-3 * radius, 1, j, (t0, t1, float(mid[2]))))
    prims.sort(key=lambda p: (-p[0], p[1], p[2]))

    ids = np.zeros((size, size), np.int32)
    for dist, kind, i, payload in prims:
        if kind == 0:
            mat, n = payload
            pts = uv[starts[i]:starts[i + 1]]
            rast.fill(ids, pts, record(_MAT_ALBEDO[mat] * model.face_jitter[i], n, mat, model.face_part[i]))
            em = model.face_edge_mat[i]
            if em >= 0 and np.ptp(pts, axis=0).min() > 6:
                rast.outline(ids, pts, record(_MAT_ALBEDO[em], n, em, model.face_part[i]))
        else:
            t0, t1, zmid = payload
            a, b = seg_q[i]
            axis = (b - a) / (np.linalg.norm(b - a) + 1e-12)
            # cylinder normal that best faces sun + viewer, in the plane perpendicular to the axis
            v = -(a + b) / 2
            v /= np.linalg.norm(v)
            want = spec.sun + v
            n = want - (want @ axis) * axis
            n = n / (np.linalg.norm(n) + 1e-12)
            mat = model.seg_mat[i]
            width = int(round(min(max(f * model.seg_width[i] / zmid, 1.0), max(1.0, model.seg_max_px[i] * scale384))))
            p0, p1 = (seg_uv[i, 0] + (seg_uv[i, 1] - seg_uv[i, 0]) * t for t in (t0, t1))
            rast.line(ids, p0, p1, record(_MAT_ALBEDO[mat], n, mat, model.seg_part[i]), width)

    albedo, normal, material, part = zip(*records)
    return Rasterized(ids=ids, albedo=np.asarray(albedo, np.float32), normal=np.asarray(normal, np.float32),
                      material=np.asarray(material, np.int32), part=np.asarray(part, np.uint8), focal=f, centre=c)


def render_view(model: SpacecraftModel, spec: ViewSpec, size: int, rng: np.random.Generator,
                rasterizer: str = "cv2") -> SyntheticView:
    """Render one view of ``model`` at ``size`` x ``size``: rasterise, shade, blur, hard case, sensor noise."""
    r = rasterize(model, spec, size, rng, rasterizer)
    ids, f, c = r.ids, r.focal, r.centre
    scale384 = size / 384.0
    mask = ids > 0

    # --- deferred shading on the object's bounding box -----------------------------------------
    img = render_background(spec.background, rng, size, spec.sun)
    ys, xs = np.nonzero(mask)
    if len(ys):
        idp = ids[ys, xs]                               # shade foreground pixels only (1-D)
        alb, nrm, matp = r.albedo[idp], r.normal[idp], r.material[idp]
        crinkle = _MAT_CRINKLE[matp]
        if crinkle.any():
            y0, x0 = ys.min(), xs.min()
            hh, ww = ys.max() + 1 - y0, xs.max() + 1 - x0
            # crinkle wavelength ~3 px at 384 (image space: foil creases are small)
            cells = min(max(4, int(max(hh, ww) / (3 * scale384 + 1))), 160)
            for k in range(2):
                field = _smooth_noise(rng, hh, ww, [cells, cells // 3 + 1], [0.5, 0.5])
                nrm[:, k] += crinkle * field[ys - y0, xs - x0]
            nrm /= np.linalg.norm(nrm, axis=-1, keepdims=True) + 1e-6
        view = np.stack([-(xs - c) / f, -(ys - c) / f, -np.ones(len(xs))], -1).astype(np.float32)
        view /= np.linalg.norm(view, axis=-1, keepdims=True)
        sun = spec.sun.astype(np.float32)
        half = view + sun
        half /= np.linalg.norm(half, axis=-1, keepdims=True) + 1e-6
        ndl = np.clip(nrm @ sun, 0, None)
        fill = 0.16 * np.clip(nrm @ (-sun), 0, None)  # earthshine / scattered fill light
        ndh = np.clip((nrm * half).sum(-1), 0, None)
        spec_term = _MAT_KS[matp] * ndh ** _MAT_SHIN[matp] * (ndl > 0)
        img[ys, xs] = alb * (0.05 + 1.05 * ndl + fill)[:, None] + 1.4 * spec_term[:, None]

    img = cv2.GaussianBlur(img, (0, 0), 0.45 * scale384 + 0.25)  # optics PSF
    img = apply_hard_case(img, spec.hard_case, rng, mask)
    img += 0.006 * rng.standard_normal(img.shape, dtype=np.float32)  # baseline sensor noise
    np.clip(img, 0, 1, out=img)
    return SyntheticView(image=(img * 255 + 0.5).astype(np.uint8), mask=mask, parts=r.part[ids], spacecraft=model.name,
                         background=spec.background, hard_case=spec.hard_case,
                         area_fraction=float(mask.mean()))


def apply_hard_case(img: np.ndarray, case: str, rng: np.random.Generator, mask: np.ndarray) -> np.ndarray:
    """Image-only degradations (ground truth unchanged): glare | flare | underexposed | noise | blur."""
    size = img.shape[0]
    s = size / 384.0
    if case == "none":
        return img
    if case in ("glare", "flare"):
        ys, xs = np.nonzero(mask)
        if case == "glare" and len(ys):
            k = rng.integers(len(ys))
            src = np.array([xs[k], ys[k]], float) + rng.normal(0, 0.05 * size, 2)
        else:
            src = rng.uniform(-0.1, 1.1, 2) * size
        yy, xx = np.mgrid[0:size, 0:size].astype(np.float32)
        r2 = (xx - src[0]) ** 2 + (yy - src[1]) ** 2
        if case == "glare":
            sigma = rng.uniform(0.12, 0.3) * size
            img = (img * rng.uniform(1.2, 1.8) + (rng.uniform(0.4, 1.0) * np.exp(-r2 / (2 * sigma ** 2)))[..., None]
                   * np.array([1.0, 0.97, 0.9], np.float32))
            bright = np.clip(img - 0.8, 0, None)
            img = img + 2.0 * cv2.GaussianBlur(bright, (0, 0), 8 * s + 1)
        else:
            img = img + (np.exp(-r2 / (2 * (0.03 * size) ** 2)) * 1.5
                         + np.exp(-r2 / (2 * (0.12 * size) ** 2)) * 0.25)[..., None]
            layer = np.zeros_like(img)
            centre = np.array([size / 2, size / 2])
            for _ in range(int(rng.integers(4, 7))):  # ghosts along the line through the image centre
                t = rng.uniform(0.4, 2.2)
                p = src + t * (centre - src)
                rad = int(rng.uniform(0.02, 0.1) * size) + 1
                colr = tuple(float(v) for v in rng.uniform(0.05, 0.25, 3))
                cv2.circle(layer, (int(p[0]), int(p[1])), rad, colr, -1, cv2.LINE_AA)
            th = np.deg2rad(rng.uniform(0, 180))
            for k in range(int(rng.integers(2, 4))):  # starburst streaks
                a = th + k * np.pi / 3
                d = np.array([math.cos(a), math.sin(a)]) * size
                cv2.line(layer, tuple(int(v) for v in src - d), tuple(int(v) for v in src + d),
                         (0.35, 0.35, 0.3), max(1, int(round(s))), cv2.LINE_AA)
            img = img + cv2.GaussianBlur(layer, (0, 0), 1.5 * s + 0.5)
        return img
    if case == "underexposed":
        return img * rng.uniform(0.06, 0.22)
    if case == "noise":
        sigma = rng.uniform(0.04, 0.1)
        img = img + rng.normal(0, 1, img.shape).astype(np.float32) * (sigma * (0.5 + np.sqrt(np.clip(img, 0, 1))))
        hot = rng.random(img.shape[:2]) < 2e-3
        img[hot] = 1.0
        return img
    if case == "blur":
        if rng.random() < 0.5:
            return cv2.GaussianBlur(img, (0, 0), rng.uniform(1.2, 2.8) * s + 0.3)
        length = max(3, int(rng.uniform(7, 17) * s))
        kern = np.zeros((length, length), np.float32)
        cv2.line(kern, (0, length // 2), (length - 1, length // 2), 1.0, 1)
        rot = cv2.getRotationMatrix2D(((length - 1) / 2, (length - 1) / 2), rng.uniform(0, 180), 1.0)
        kern = cv2.warpAffine(kern, rot, (length, length))
        return cv2.filter2D(img, -1, kern / max(kern.sum(), 1e-6))
    raise ValueError(f"unknown hard case {case!r}")


@dataclasses.dataclass(frozen=True)
class PlannedSpacecraft:
    name: str
    split: str   # train | val | test
    group: str   # train | val | <test group>
    views: int


def synthetic_plan(cfg: dict) -> list[PlannedSpacecraft]:
    """Plan the spacecraft-disjoint split mirroring SpaceSense-Bench (eq:spacecraft-disjoint).

    Parameters
    ----------
    cfg : dict
        The validated ``data.synthetic`` section (spacecraft and views per split, the test groups).

    Returns
    -------
    list of PlannedSpacecraft
        One per spacecraft, train then val then each test group; its name encodes its group.
    """
    plan = [PlannedSpacecraft(f"syn-train-{i:02d}", "train", "train", int(cfg["train_views"]))
            for i in range(int(cfg["train_spacecraft"]))]
    plan += [PlannedSpacecraft(f"syn-val-{i:02d}", "val", "val", int(cfg["val_views"]))
             for i in range(int(cfg["val_spacecraft"]))]
    for g in cfg["test_groups"]:
        plan += [PlannedSpacecraft(f"syn-{g}-{i}", "test", str(g), int(cfg["test_views"]))
                 for i in range(int(cfg["test_spacecraft_per_group"]))]
    return plan


def sampling_options(cfg: Mapping) -> dict:
    """Pick the view-sampling knobs out of ``data.synthetic``: the keywords :func:`sample_view` takes.

    Parameters
    ----------
    cfg : Mapping
        The validated ``data.synthetic`` section.

    Returns
    -------
    dict
        ``{keyword: value}`` for each keyword-only parameter of :func:`sample_view` that ``cfg`` holds.
    """
    keys = [p.name for p in inspect.signature(sample_view).parameters.values() if p.kind is p.KEYWORD_ONLY]
    return {k: cfg[k] for k in keys if k in cfg}


def view_rng(seed: int, spacecraft: str, view_index: int) -> np.random.Generator:
    """Seed one view's generator from ``(seed, spacecraft, view index)`` alone.

    Parameters
    ----------
    seed : int
        ``data.seed``.
    spacecraft : str
        The spacecraft's name.
    view_index : int
        The view's index.

    Returns
    -------
    numpy.random.Generator
        The same stream in every process, whatever else was drawn.
    """
    return np.random.default_rng([int(seed), stable_hash(spacecraft), int(view_index)])


def generate_view(model: SpacecraftModel, view_index: int, size: int, seed: int,
                  view_options: dict | None = None, rasterizer: str = "cv2") -> SyntheticView:
    """Render view ``view_index`` of ``model`` at ``size`` px, deterministically (same inputs, same pixels).

    Parameters
    ----------
    model : SpacecraftModel
        The spacecraft (:func:`make_spacecraft`).
    view_index : int
        Which view.
    size : int
        The image side in pixels (``data.resolution``).
    seed : int
        ``data.seed``.
    view_options : dict, optional
        Keywords of :func:`sample_view` (:func:`sampling_options`); None: its defaults.
    rasterizer : str
        ``cv2`` or ``numpy`` (:func:`rasterize`).

    Returns
    -------
    SyntheticView
        RGB image, ground-truth mask and part labels, with the view's background, hard case and area fraction.
    """
    rng = view_rng(seed, model.name, view_index)
    spec = sample_view(rng, **(view_options or {}))
    return render_view(model, spec, size, rng, rasterizer=rasterizer)
