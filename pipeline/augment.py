"""Target-consistent augmentation: an image and every target trained on it move together.

Pure functions on numpy arrays (no torch, no file): :func:`augment_sample` augments one training image
and its targets, :func:`augment_batch` a batch with one seeded generator per image.  The training loop
(:mod:`pipeline.training.loop`, ``train.augment``; on in the ``strong`` recipe only) calls
:func:`augment_batch` on every batch; with augmentation off nothing here runs and the batches are the
ones the paper and stable recipes always trained on.

Targets (``targets`` mapping; each is optional except ``mask``)
  * ``mask`` bool [H,W]: the region target (the voted pseudo-mask M^T, eq:majority-vote; the AFS
    control's fused mask; the supervised ceiling's reference mask);
  * ``sdf`` float32 [H,W] (eq:sdf-target) and ``skeleton`` bool [H,W]: the pseudo-geometry targets;
  * ``anchor`` float32 [H,W]: the frozen Stage-I probabilities of the adaptive method's L_anchor;
  * ``area`` float (eq:pseudo-area) and ``gate`` float (eq:reliability-gate): per-image scalars.

Geometric augmentation, in this order:
  1. **flips and 90 degree rotations** (``hflip``, ``vflip``, ``rot90``): applied to the image and to
     ``mask``, ``sdf``, ``skeleton`` and ``anchor`` alike.  These are exact: the distance transform of
     eq:sdf-target is exact Euclidean between pixel centres and its 0.95 quantile runs over all pixels,
     and the skeleton's 3x3 neighbourhood is symmetric, so flipping/rotating the stored targets gives
     bit for bit ``sdf_target`` / ``skeleton_target`` of the flipped mask (tests/test_augment.py checks
     it).  No target is recomputed; area is unchanged.  A 90 degree rotation of a non-square image would
     change its shape: only the 180 degree one is drawn there.
  2. **scale / crop jitter** (``scale_probability``, ``scale_range``): a window of (H/s, W/s) pixels with
     s log-uniform in ``scale_range``, placed uniformly at random (s > 1 zooms in on part of the frame;
     s < 1 zooms out and the frame is padded with black -- space, the dark lab), resized back to [H,W]:
     the image and ``anchor`` bilinearly, ``mask`` by nearest neighbour.  Distances do not survive a
     resampling, so ``sdf`` and ``skeleton`` are **recomputed** from the augmented mask
     (:func:`pipeline.geometry.pseudo_targets` with the geometry stage's constants) and ``area`` is the
     augmented mask's area ratio (:func:`pipeline.geometry.area_ratio`).

Photometric augmentation of the image only (``photometric_probability`` per image, then each part with
its own draw), for spacecraft imagery: brightness (additive), contrast (about the image mean), gamma
(log-uniform), saturated glare (a bright Gaussian spot added and clipped at 255, as the sun on foil or
a lens flare does), blur (Gaussian, defocus or motion), sensor noise (Gaussian, read noise).  The
targets do not change: the object is where it was.

The gate (decision, docs/decisions.md): ``gate`` is passed through unchanged.  g_i (eq:reliability-gate)
is the reliability of the teacher's pseudo-label of image i -- from the prompts' agreement, their
validity and the area against the training median -- and no augmentation changes what the teacher said
or how much to trust it: an image flipped, cropped or darkened carries the same label with the same
reliability.  (The area factor of the gate is computed once from the un-augmented image; a crop that
changes the visible area does not re-open that question.)

Seeding: each image draws from ``numpy.random.default_rng(seed_i)``; :func:`augment_batch` takes one
seed per image (the training loop uses ``[run seed, epoch, image index]``), so the same seeds give the
same augmented batch, whatever else the batch holds.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping, Sequence

import numpy as np

from pipeline.geometry import area_ratio, pseudo_targets
from pipeline.params import PAPER

#: the pixel targets that move with the image; ``sdf``/``skeleton`` are recomputed after a rescale
PIXEL_TARGETS = ("mask", "sdf", "skeleton", "anchor")


@dataclasses.dataclass(frozen=True)
class AugmentSpec:
    """The augmentation's probabilities and magnitudes (the ``train.augmentation`` params section)."""

    hflip: float
    vflip: float
    rot90: bool
    scale_probability: float
    scale_range: tuple[float, float]
    photometric_probability: float
    brightness: float
    contrast: float
    gamma: float
    glare_probability: float
    blur_probability: float
    blur_sigma: float
    noise_std: float

    @classmethod
    def from_params(cls, section: Mapping[str, Any]) -> "AugmentSpec":
        """From a validated ``train.augmentation`` mapping."""
        fields = {f.name for f in dataclasses.fields(cls)}
        values = {k: v for k, v in section.items() if k in fields}
        values["scale_range"] = tuple(float(x) for x in values["scale_range"])
        return cls(**values)


#: the schema's defaults (pipeline.params, their one place)
DEFAULT_SPEC = AugmentSpec.from_params(PAPER.train.augmentation.model_dump())


@dataclasses.dataclass(frozen=True)
class GeometryConstants:
    """The constants the geometry stage computed the SDF and skeleton with (``geometry.*`` params)."""

    quantile: float = PAPER.geometry.sdf_quantile
    min_scale: float = PAPER.geometry.sdf_min_scale
    min_distance: float = PAPER.geometry.skeleton_min_distance


# --------------------------------------------------------------------------------------------------
# geometric
# --------------------------------------------------------------------------------------------------
def dihedral(x: np.ndarray, k: int, hflip: bool, vflip: bool) -> np.ndarray:
    """``x`` [H,W,...] rotated by k x 90 degrees (counter-clockwise, ``numpy.rot90``), then flipped
    left-right and up-down as asked; a contiguous copy."""
    out = np.rot90(x, k % 4, axes=(0, 1))
    if hflip:
        out = out[:, ::-1]
    if vflip:
        out = out[::-1]
    return np.ascontiguousarray(out)


def crop_window(shape: tuple[int, int], scale: float, rng: np.random.Generator) -> tuple[float, float, float, float]:
    """A window (x0, y0, w, h) in input pixels for zoom factor ``scale`` (window = frame / scale),
    placed uniformly: inside the frame when it is smaller, around the frame when it is larger."""
    h, w = shape
    wh, ww = h / scale, w / scale
    y0 = rng.uniform(min(0.0, h - wh), max(0.0, h - wh))
    x0 = rng.uniform(min(0.0, w - ww), max(0.0, w - ww))
    return x0, y0, ww, wh


def resample(x: np.ndarray, window: tuple[float, float, float, float], nearest: bool) -> np.ndarray:
    """``x`` [H,W] or [H,W,C] resampled so that ``window`` (x0, y0, w, h) fills the [H,W] frame:
    bilinear, or nearest neighbour for masks; outside the input is 0 (black, background)."""
    import cv2

    h, w = x.shape[:2]
    x0, y0, ww, wh = window
    sx, sy = ww / w, wh / h
    # output pixel centre (u, v) -> input point (x0 + (u + .5) sx - .5, y0 + (v + .5) sy - .5)
    m = np.array([[sx, 0.0, x0 + 0.5 * sx - 0.5], [0.0, sy, y0 + 0.5 * sy - 0.5]], np.float64)
    src = x.astype(np.uint8) if x.dtype == bool else x
    out = cv2.warpAffine(np.ascontiguousarray(src), m, (w, h),
                         flags=(cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR) | cv2.WARP_INVERSE_MAP,
                         borderMode=cv2.BORDER_CONSTANT, borderValue=0)
    if out.ndim < x.ndim:  # cv2 drops a single channel
        out = out[..., None]
    return out.astype(bool) if x.dtype == bool else out


def recompute_geometry(mask: np.ndarray, geometry: GeometryConstants) -> tuple[np.ndarray, np.ndarray, float]:
    """(sdf, skeleton, area) of ``mask``: eq:sdf-target, the skeleton and eq:pseudo-area, exactly as the
    geometry stage computes them (:func:`pipeline.geometry.pseudo_targets`)."""
    sdf, skel, _ = pseudo_targets(mask[None], quantile=geometry.quantile, min_scale=geometry.min_scale,
                                  min_distance=geometry.min_distance)
    return sdf[0], skel[0], area_ratio(mask)


# --------------------------------------------------------------------------------------------------
# photometric
# --------------------------------------------------------------------------------------------------
def photometric(image: np.ndarray, spec: AugmentSpec, rng: np.random.Generator) -> np.ndarray:
    """``image`` uint8 [H,W,C] with brightness, contrast, gamma, glare, blur and sensor noise, each
    drawn from ``rng`` (the order of the draws is fixed); uint8 out."""
    x = image.astype(np.float32) / 255.0
    h, w = x.shape[:2]
    b = rng.uniform(-spec.brightness, spec.brightness)
    c = math.exp(rng.uniform(-math.log1p(spec.contrast), math.log1p(spec.contrast)))
    g = math.exp(rng.uniform(-math.log1p(spec.gamma), math.log1p(spec.gamma)))
    x = (x - x.mean()) * c + x.mean() + b
    x = np.clip(x, 0.0, 1.0) ** g
    if rng.random() < spec.glare_probability:  # a saturated spot: sun glint on foil, a lens flare
        cy, cx = rng.uniform(0, h), rng.uniform(0, w)
        r = rng.uniform(0.05, 0.15) * max(h, w)
        yy, xx = np.mgrid[0:h, 0:w]
        spot = np.exp(-((yy - cy) ** 2 + (xx - cx) ** 2) / (2 * r * r)).astype(np.float32)
        x = x + rng.uniform(1.2, 2.5) * spot[..., None]  # peak above full scale: the core saturates
    if rng.random() < spec.blur_probability:
        import cv2

        sigma = rng.uniform(0.3, max(spec.blur_sigma, 0.3))
        x = cv2.GaussianBlur(np.ascontiguousarray(x), (0, 0), sigma).reshape(x.shape)
    if spec.noise_std > 0:
        x = x + rng.normal(0.0, rng.uniform(0.0, spec.noise_std), size=x.shape).astype(np.float32)
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)


# --------------------------------------------------------------------------------------------------
# one image, one batch
# --------------------------------------------------------------------------------------------------
def augment_sample(image: np.ndarray, targets: Mapping[str, Any], rng: np.random.Generator,
                   spec: AugmentSpec = DEFAULT_SPEC, geometry: GeometryConstants = GeometryConstants()
                   ) -> tuple[np.ndarray, dict]:
    """One image uint8 [H,W,C] and its ``targets`` (module docstring) augmented with draws from ``rng``.

    Returns (image, targets): new arrays, the inputs untouched; ``gate`` and any key this module does
    not know are passed through unchanged.
    """
    h, w = image.shape[:2]
    out = dict(targets)
    pixel = {k: np.asarray(targets[k]) for k in PIXEL_TARGETS if targets.get(k) is not None}
    # 1. flips and rotations: exact for every target
    k = int(rng.integers(4)) if spec.rot90 else 0
    if h != w:
        k = 2 * (k % 2)  # only 0 or 180 degrees keep a non-square frame's shape
    hf, vf = bool(rng.random() < spec.hflip), bool(rng.random() < spec.vflip)
    image = dihedral(image, k, hf, vf)
    pixel = {name: dihedral(v, k, hf, vf) for name, v in pixel.items()}
    # 2. scale / crop: resample image, mask (nearest) and anchor; recompute the geometry from the mask
    if rng.random() < spec.scale_probability:
        lo, hi = spec.scale_range
        s = math.exp(rng.uniform(math.log(lo), math.log(hi)))
        window = crop_window((h, w), s, rng)
        image = resample(image, window, nearest=False)
        soft = pixel["mask"].dtype.kind == "f"  # train.soft_targets: the agreement map resamples bilinearly
        pixel["mask"] = resample(pixel["mask"] if soft else pixel["mask"].astype(bool), window, nearest=not soft)
        if "anchor" in pixel:
            pixel["anchor"] = resample(pixel["anchor"].astype(np.float32), window, nearest=False)
        sdf, skel, area = recompute_geometry(pixel["mask"] >= 0.5 if soft else pixel["mask"], geometry)
        if "sdf" in pixel:
            pixel["sdf"] = sdf
        if "skeleton" in pixel:
            pixel["skeleton"] = skel
        if "area" in out:
            out["area"] = area
    # 3. photometric: the image only
    if rng.random() < spec.photometric_probability:
        image = photometric(image, spec, rng)
    out.update(pixel)
    return image, out


def augment_batch(images: np.ndarray, targets: Mapping[str, np.ndarray], seeds: Sequence,
                  spec: AugmentSpec = DEFAULT_SPEC, geometry: GeometryConstants = GeometryConstants()
                  ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """A batch: ``images`` uint8 [B,H,W,C], ``targets`` name -> [B,...] arrays (pixel targets [B,H,W],
    scalars [B]), ``seeds`` one ``numpy.random.default_rng`` seed per image.  Returns new arrays of the
    same shapes and dtypes."""
    if len(seeds) != len(images):
        raise ValueError(f"augment_batch: {len(seeds)} seeds for {len(images)} images")
    out_images = np.empty_like(images)
    out = {k: np.empty_like(np.asarray(v)) for k, v in targets.items()}
    for i, seed in enumerate(seeds):
        img, tgt = augment_sample(images[i], {k: v[i] for k, v in targets.items()},
                                  np.random.default_rng(seed), spec, geometry)
        out_images[i] = img
        for k, v in tgt.items():
            out[k][i] = v
    return out_images, out
