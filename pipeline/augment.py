"""Target-consistent augmentation (``train.augment``; docs/decisions.md, "Augmentation").

An image and every target trained on it move together: flips exactly, a rescale with its SDF, skeleton and area
recomputed; the gate is passed through.  Numpy only, one seeded generator per image.
"""

from __future__ import annotations

import dataclasses
import math
from typing import Any, Mapping, Sequence

import numpy as np

from pipeline.geometry import area_ratio, pseudo_targets
from pipeline.params import PAPER

__all__ = ["AugmentSpec", "GeometryConstants", "soft_region", "hard_region", "recompute_geometry", "lens_flare",
           "augment_batch"]

#: the pixel targets that move with the image; ``sdf``/``skeleton`` are recomputed after a rescale
PIXEL_TARGETS = ("mask", "sdf", "skeleton", "anchor")


@dataclasses.dataclass(frozen=True)
class AugmentSpec:
    """The augmentation's probabilities and magnitudes (the ``train.augmentation`` params section).

    Each field is the params key of its name; its range and default live in
    :class:`pipeline.params.AugmentParams`.

    Attributes
    ----------
    hflip : float
        Probability of a left-right flip (``train.augmentation.hflip``).
    vflip : float
        Probability of an up-down flip (``train.augmentation.vflip``).
    rot90 : bool
        Rotate by a uniformly drawn multiple of 90 degrees (``train.augmentation.rot90``; 0 or 180 for a
        non-square frame).
    scale_probability : float
        Probability of a scale/crop jitter (``train.augmentation.scale_probability``).
    scale_range : tuple[float, float]
        The zoom factor's range, drawn log-uniform; < 1 zooms out, padding black
        (``train.augmentation.scale_range``).
    photometric_probability : float
        Probability of the photometric part (``train.augmentation.photometric_probability``).
    brightness : float
        Largest additive brightness shift, a fraction of full scale (``train.augmentation.brightness``).
    contrast : float
        x: the contrast factor about the image mean is drawn in [1/(1+x), 1+x] (``train.augmentation.contrast``).
    gamma : float
        x: gamma is drawn in [1/(1+x), 1+x], log-uniform (``train.augmentation.gamma``).
    glare_probability : float
        Probability of a saturated glare spot (``train.augmentation.glare_probability``).
    flare_probability : float
        Probability of a lens flare (:func:`lens_flare`; ``train.augmentation.flare_probability``).
    exposure_range : tuple[float, float]
        The exposure gain's range, drawn log-uniform and applied first; ``(1, 1)`` draws nothing
        (``train.augmentation.exposure_range``).
    blur_probability : float
        Probability of a Gaussian blur (``train.augmentation.blur_probability``).
    blur_sigma : float
        Largest blur sigma in pixels (``train.augmentation.blur_sigma``).
    noise_std : float
        Largest Gaussian sensor-noise std, a fraction of full scale (``train.augmentation.noise_std``).
    """

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
    flare_probability: float
    exposure_range: tuple[float, float]
    blur_probability: float
    blur_sigma: float
    noise_std: float

    @classmethod
    def from_params(cls, section: Mapping[str, Any]) -> "AugmentSpec":
        """Build the spec from a validated ``train.augmentation`` mapping.

        Parameters
        ----------
        section : Mapping[str, Any]
            The section's values (keys that are no field are ignored).

        Returns
        -------
        AugmentSpec
            The spec, ``scale_range`` as a tuple of floats.

        Raises
        ------
        KeyError
            ``section`` lacks ``scale_range`` or ``exposure_range``.
        TypeError
            ``section`` lacks another field.
        """
        fields = {f.name for f in dataclasses.fields(cls)}
        values = {k: v for k, v in section.items() if k in fields}
        for name in ("scale_range", "exposure_range"):
            values[name] = tuple(float(x) for x in values[name])
        return cls(**values)


#: the schema's defaults (pipeline.params, their one place)
DEFAULT_SPEC = AugmentSpec.from_params(PAPER.train.augmentation.model_dump())


@dataclasses.dataclass(frozen=True)
class GeometryConstants:
    """The constants the geometry stage computed the SDF and skeleton with (``geometry.*`` params).

    The defaults are the schema's (:data:`pipeline.params.PAPER`).

    Attributes
    ----------
    quantile : float
        q of the SDF's scale s = q-quantile of |D~| (eq:sdf-target; ``geometry.sdf_quantile``).
    min_scale : float
        s = 1 when the quantile is below this (eq:sdf-target; ``geometry.sdf_min_scale``).
    min_distance : float
        Skeleton points with an interior distance d_in at most this (px) are dropped
        (``geometry.skeleton_min_distance``).
    """

    quantile: float = PAPER.geometry.sdf_quantile
    min_scale: float = PAPER.geometry.sdf_min_scale
    min_distance: float = PAPER.geometry.skeleton_min_distance


def soft_region(mask: Any) -> bool:
    """Tell whether a region target is the agreement map A, not the voted mask M^T.

    A (eq:agreement-map) is floats (``train.soft_targets``), M^T (eq:majority-vote) booleans.  Read from the dtype,
    never the values: no GPU sync per batch.

    Parameters
    ----------
    mask : array-like
        A region target with a ``dtype`` (numpy array or torch tensor).

    Returns
    -------
    bool
        True for a floating-point target.
    """
    return np.dtype(mask.dtype).kind == "f"


def hard_region(mask: np.ndarray) -> np.ndarray:
    """Return the boolean region of a target: M = [A >= 1/2] (eq:majority-vote) for a soft one, else the mask.

    Parameters
    ----------
    mask : np.ndarray
        The agreement map A (floats) or a mask (booleans or integers).

    Returns
    -------
    np.ndarray
        The boolean region, of ``mask``'s shape.
    """
    return mask >= 0.5 if soft_region(mask) else mask.astype(bool)


def dihedral(x: np.ndarray, k: int, hflip: bool, vflip: bool) -> np.ndarray:
    """Rotate ``x`` [H,W,...] by k x 90 degrees counter-clockwise, then flip it as asked; a contiguous copy."""
    out = np.rot90(x, k % 4, axes=(0, 1))
    if hflip:
        out = out[:, ::-1]
    if vflip:
        out = out[::-1]
    return np.ascontiguousarray(out)


def resample(x: np.ndarray, window: tuple[float, float, float, float], nearest: bool) -> np.ndarray:
    """Resample ``x`` [H,W(,C)] so that ``window`` fills the frame, bilinear or nearest; 0 outside the input."""
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
    """Compute the SDF, skeleton and area of ``mask`` as the geometry stage does.

    D = clip(D~ / s, -1, 1), D~ = d_in - d_out (eq:sdf-target); K = Skel(M); a = 1/(HW) sum_x M(x)
    (eq:pseudo-area).

    Parameters
    ----------
    mask : np.ndarray
        The boolean region M [H,W].
    geometry : GeometryConstants
        The constants the geometry stage used.

    Returns
    -------
    sdf : np.ndarray
        The normalised SDF target D [H,W].
    skeleton : np.ndarray
        The skeleton target K [H,W].
    area : float
        The area ratio a.
    """
    sdf, skel, _ = pseudo_targets(mask[None], quantile=geometry.quantile, min_scale=geometry.min_scale,
                                  min_distance=geometry.min_distance)
    return sdf[0], skel[0], area_ratio(mask)


def lens_flare(h: int, w: int, rng: np.random.Generator) -> np.ndarray:
    """Draw a lens flare's added light: a bright source and ghost discs along a line through it.

    The model of albumentations' ``RandomSunFlare``, not the synthetic benchmark's renderer: the source lies
    anywhere in or just outside the frame (the sun often is), with a saturating core and a wide halo; 3 to 7
    ghosts (internal reflections) sit along a line through it at a random angle, each a soft-edged disc with its
    own tint.  Sizes scale with D = max(h, w)::

        L(p) = a_c exp(-|p - s|^2 / 2 r_c^2) + a_h exp(-|p - s|^2 / 2 r_h^2) + sum_k t_k disc(p; s + u_k d, r_k)

    Parameters
    ----------
    h, w : int
        The frame's height and width.
    rng : np.random.Generator
        The image's own generator.

    Returns
    -------
    np.ndarray
        float32 [h, w, 3] light to add to an image in [0, 1] (the core exceeds 1: it saturates).
    """
    d = float(max(h, w))
    sy, sx = rng.uniform(-0.1, 1.1) * h, rng.uniform(-0.1, 1.1) * w
    yy, xx = np.mgrid[0:h, 0:w].astype(np.float32)
    r2 = (yy - sy) ** 2 + (xx - sx) ** 2
    rc, rh = rng.uniform(0.015, 0.04) * d, rng.uniform(0.08, 0.2) * d
    light = rng.uniform(1.0, 2.0) * np.exp(-r2 / (2 * rc * rc)) + rng.uniform(0.1, 0.4) * np.exp(-r2 / (2 * rh * rh))
    out = np.repeat(light[..., None], 3, axis=2).astype(np.float32)
    theta = rng.uniform(0.0, math.pi)
    dy, dx = math.sin(theta), math.cos(theta)
    for _ in range(int(rng.integers(3, 8))):
        u, r = rng.uniform(-1.0, 1.0) * d, rng.uniform(0.01, 0.08) * d
        tint = rng.uniform(0.05, 0.3) * rng.uniform(0.7, 1.0, 3).astype(np.float32)
        dist = np.sqrt((yy - sy - u * dy) ** 2 + (xx - sx - u * dx) ** 2)
        out += np.clip(r - dist + 0.5, 0.0, 1.0)[..., None] * tint  # a one-pixel soft edge
    return out


def photometric(image: np.ndarray, spec: AugmentSpec, rng: np.random.Generator) -> np.ndarray:
    """Apply exposure, brightness, contrast, gamma, glare, a lens flare, blur and sensor noise to uint8 [H,W,C].

    Each is drawn from ``rng``.  A part at its "none" value (``exposure_range`` (1, 1), ``flare_probability`` 0)
    draws nothing, so the other parts' draws are those made without it.
    """
    x = image.astype(np.float32) / 255.0
    h, w = x.shape[:2]
    if spec.exposure_range != (1.0, 1.0):  # the scene's light before the camera's other changes
        lo, hi = spec.exposure_range
        x = x * math.exp(rng.uniform(math.log(lo), math.log(hi)))
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
    if spec.flare_probability > 0 and rng.random() < spec.flare_probability:
        x = x + lens_flare(h, w, rng)
    if rng.random() < spec.blur_probability:
        import cv2

        sigma = rng.uniform(0.3, max(spec.blur_sigma, 0.3))
        x = cv2.GaussianBlur(np.ascontiguousarray(x), (0, 0), sigma).reshape(x.shape)
    if spec.noise_std > 0:
        x = x + rng.normal(0.0, rng.uniform(0.0, spec.noise_std), size=x.shape).astype(np.float32)
    return np.clip(np.rint(x * 255.0), 0, 255).astype(np.uint8)


def augment_sample(image: np.ndarray, targets: Mapping[str, Any], rng: np.random.Generator,
                   spec: AugmentSpec = DEFAULT_SPEC, geometry: GeometryConstants = GeometryConstants()
                   ) -> tuple[np.ndarray, dict]:
    """Augment one image and its targets together with draws from ``rng``; new arrays.

    Parameters
    ----------
    image : np.ndarray
        uint8 [H,W,C].
    targets : Mapping[str, Any]
        ``mask`` (A or M^T), and optionally ``sdf``, ``skeleton``, ``anchor`` [H,W,...] and ``area``; any other
        target passes through.
    rng : np.random.Generator
        The image's own generator.
    spec : AugmentSpec, optional
        Probabilities and magnitudes (default: the schema's ``train.augmentation``).
    geometry : GeometryConstants, optional
        The constants SDF and skeleton are recomputed with after a rescale.

    Returns
    -------
    image : np.ndarray
        The augmented image, uint8 [H,W,C].
    targets : dict
        The augmented targets, the same keys.
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
        wh, ww = h / s, w / s  # a window (x0, y0, w, h) of frame / s input pixels, uniformly inside or around it
        y0 = rng.uniform(min(0.0, h - wh), max(0.0, h - wh))
        window = (rng.uniform(min(0.0, w - ww), max(0.0, w - ww)), y0, ww, wh)
        image = resample(image, window, nearest=False)
        soft = soft_region(pixel["mask"])  # train.soft_targets: the agreement map resamples bilinearly
        pixel["mask"] = resample(pixel["mask"] if soft else pixel["mask"].astype(bool), window, nearest=not soft)
        if "anchor" in pixel:
            pixel["anchor"] = resample(pixel["anchor"].astype(np.float32), window, nearest=False)
        region = hard_region(pixel["mask"])
        if "sdf" in pixel or "skeleton" in pixel:  # Stage I trains on neither: no distance transforms per step
            sdf, skel, _ = recompute_geometry(region, geometry)
            pixel.update({k: v for k, v in (("sdf", sdf), ("skeleton", skel)) if k in pixel})
        if "area" in out:
            out["area"] = area_ratio(region)
    # 3. photometric: the image only
    if rng.random() < spec.photometric_probability:
        image = photometric(image, spec, rng)
    out.update(pixel)
    return image, out


def augment_batch(images: np.ndarray, targets: Mapping[str, np.ndarray], seeds: Sequence,
                  spec: AugmentSpec = DEFAULT_SPEC, geometry: GeometryConstants = GeometryConstants()
                  ) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """Augment every image of a batch and its targets, each with a generator of its own seed.

    Flips and rotations move every pixel target exactly; a rescale resamples image, mask and anchor and
    recomputes SDF, skeleton (eq:sdf-target) and area (eq:pseudo-area) from the mask; the photometric part
    changes the image only.

    Parameters
    ----------
    images : np.ndarray
        uint8 [B,H,W,C].
    targets : Mapping[str, np.ndarray]
        Target name -> [B,...]: ``mask`` (A or M^T), optional ``sdf``, ``skeleton``, ``anchor``, ``area``; any
        other passes through.
    seeds : Sequence
        One seed per image (``numpy.random.default_rng``'s), so that an image's draws do not depend on its batch.
    spec : AugmentSpec, optional
        Probabilities and magnitudes (default: the schema's ``train.augmentation``).
    geometry : GeometryConstants, optional
        The constants SDF and skeleton are recomputed with after a rescale (default: the schema's ``geometry.*``).

    Returns
    -------
    images : np.ndarray
        The augmented images, ``images``' shape and dtype.
    targets : dict[str, np.ndarray]
        The augmented targets, the same keys and shapes.

    Raises
    ------
    ValueError
        ``seeds`` does not hold one seed per image.
    """
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
