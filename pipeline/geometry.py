"""Pseudo-geometry targets and the reliability gate of the voted pseudo-mask M.

Paper, "Reliability-Aware Pseudo-Geometry Refinement": eq:sdf-target, the skeleton, eq:pseudo-area,
eq:foreground-agreement .. eq:reliability-gate.  Distances are exact Euclidean distances in pixels between
pixel centres, to the nearest pixel of the other set; the image border is not background (docs/decisions.md,
"Distances", "Skeleton").  The constants default to the paper's values (``pipeline.params.PAPER.geometry``).
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from pipeline.runtime.errors import SET, InputError

from pipeline.params import PAPER

__all__ = ["squared_distance", "sdf_target", "skeleton_target", "area_ratio", "pseudo_targets", "area_ratios",
           "foreground_agreement", "valid_ratio", "GateFactors", "gate_factors", "median_area", "NoForeground",
           "image_gates"]

# the paper's constants, from the params schema (their one place)
SDF_QUANTILE = PAPER.geometry.sdf_quantile
SDF_MIN_SCALE = PAPER.geometry.sdf_min_scale
SKELETON_MIN_DISTANCE = PAPER.geometry.skeleton_min_distance
N_PROMPTS = PAPER.geometry.n_prompts
CONF_OFFSET = PAPER.geometry.conf_offset
VALID_OFFSET = PAPER.geometry.valid_offset
AREA_TEMPERATURE = PAPER.geometry.area_temperature
AREA_FLOOR = PAPER.geometry.area_floor
EPS = PAPER.geometry.eps


def _as_mask(mask: np.ndarray, name: str = "mask") -> np.ndarray:
    mask = np.asarray(mask)
    if mask.ndim != 2:
        raise InputError(f"{name}: expected a 2-D [H,W] mask, got shape {mask.shape}")
    if mask.dtype != bool:
        if mask.dtype.kind not in "biuf" or (mask.size and not np.isin(mask, (0, 1)).all()):
            raise InputError(f"{name}: mask must be binary (bool or 0/1)")
        mask = mask.astype(bool)
    return mask


def squared_distance(nonzero: np.ndarray) -> np.ndarray:
    """Exact squared Euclidean distance from every non-zero pixel to its nearest zero pixel.

    Parameters
    ----------
    nonzero : array_like
        A [H,W] array; non-zero pixels are measured.

    Returns
    -------
    numpy.ndarray
        float32 [H,W], integer-valued (exact while d^2 < 2^22, deterministic); 0 on zero pixels.
    """
    # OpenCV's precise transform is exact in d^2 but its square root differs by one ulp with the buffer's
    # alignment: rounding d^2 back to its integer makes the result deterministic
    import cv2

    d = cv2.distanceTransform(np.ascontiguousarray(nonzero, dtype=np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    np.multiply(d, d, out=d)
    return np.rint(d, out=d)


def distance_maps(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Interior and exterior distance transforms of a mask.

    Parameters
    ----------
    mask : array_like
        A bool or 0/1 mask [H,W].

    Returns
    -------
    tuple of numpy.ndarray
        (d_in, d_out), float32 [H,W]: distance of a foreground pixel to the nearest background pixel, and of a
        background pixel to the nearest foreground pixel (0 elsewhere); meaningful only when M is neither empty
        nor full.
    """
    m8 = np.ascontiguousarray(mask, dtype=np.uint8)
    return np.sqrt(squared_distance(m8)), np.sqrt(squared_distance(1 - m8))


def _sdf_from_distances(d_in: np.ndarray, d_out: np.ndarray, quantile: float, min_scale: float) -> np.ndarray:
    raw = d_in - d_out  # D~
    absd = np.abs(raw).ravel()
    # q_0.95 with numpy's default (linear) interpolation; partition only the two order statistics needed
    pos = quantile * (absd.size - 1)
    lo = int(np.floor(pos))
    hi = min(lo + 1, absd.size - 1)
    part = np.partition(absd, (lo, hi))
    q = float(part[lo]) + (pos - lo) * (float(part[hi]) - float(part[lo]))
    s = q if q >= min_scale else 1.0
    return np.clip(raw / np.float32(s), -1.0, 1.0).astype(np.float32, copy=False)


def sdf_target(mask: np.ndarray, *, quantile: float = SDF_QUANTILE, min_scale: float = SDF_MIN_SCALE) -> np.ndarray:
    """Normalised signed distance target D^T (eq:sdf-target).

    D~ = d_in - d_out, q = q_0.95(|D~|) (linear interpolation), s = q when q >= ``min_scale`` else 1,
    D = clip(D~ / s, -1, 1); an empty M gives 0 everywhere, a full M gives 1 everywhere.

    Parameters
    ----------
    mask : array_like
        The voted mask, bool or 0/1 [H,W].
    quantile : float, optional
        The scale's quantile (default ``geometry.sdf_quantile``, 0.95).
    min_scale : float, optional
        Below this q the scale is 1 (default ``geometry.sdf_min_scale``, 1e-6).

    Returns
    -------
    numpy.ndarray
        float32 [H,W] in [-1, 1], positive inside.

    Raises
    ------
    InputError
        The mask is not 2-D or not binary.
    """
    return pseudo_targets(_as_mask(mask)[None], quantile=quantile, min_scale=min_scale)[0][0]


def _skeleton_from_distance(mask: np.ndarray, d_in: np.ndarray, min_distance: float) -> np.ndarray:
    import cv2

    # OpenCV's dilation border is the minimum value: pixels outside the frame never win
    neighbourhood_max = cv2.dilate(d_in, np.ones((3, 3), np.uint8))
    skel = (d_in > min_distance) & (d_in >= neighbourhood_max)
    if not skel.any():
        return mask.copy()  # a non-empty mask with no valid skeleton falls back to M
    return skel


def skeleton_target(mask: np.ndarray, *, min_distance: float = SKELETON_MIN_DISTANCE) -> np.ndarray:
    """Skeleton target K^T (the text after eq:sdf-target).

    K = {x : d_in(x) > ``min_distance`` and d_in(x) >= max over the 8-neighbourhood of d_in}; a non-empty mask
    with no such pixel (thin structures, a full M) falls back to K = M; an empty M gives an empty K.

    Parameters
    ----------
    mask : array_like
        The voted mask, bool or 0/1 [H,W].
    min_distance : float, optional
        Points at or below this distance are removed (default ``geometry.skeleton_min_distance``, 1 px).

    Returns
    -------
    numpy.ndarray
        bool [H,W].

    Raises
    ------
    InputError
        The mask is not 2-D or not binary.
    """
    return pseudo_targets(_as_mask(mask)[None], min_distance=min_distance)[1][0]


def area_ratio(mask: np.ndarray) -> float:
    """Pseudo-foreground area ratio a = (1/HW) sum_x M(x) (eq:pseudo-area).

    Parameters
    ----------
    mask : array_like
        The voted mask, bool or 0/1 [H,W].

    Returns
    -------
    float
        a in [0, 1]; 0 for a mask without pixels.

    Raises
    ------
    InputError
        The mask is not 2-D or not binary.
    """
    mask = _as_mask(mask)
    return float(np.count_nonzero(mask)) / mask.size if mask.size else 0.0


def pseudo_targets(masks: np.ndarray, *, quantile: float = SDF_QUANTILE, min_scale: float = SDF_MIN_SCALE,
                   min_distance: float = SKELETON_MIN_DISTANCE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Compute the SDF, skeleton and area targets of N voted masks, sharing the distance transforms.

    Per image: :func:`sdf_target`, :func:`skeleton_target` and :func:`area_ratio`, with their empty- and
    full-mask conventions.

    Parameters
    ----------
    masks : array_like
        Voted masks, bool or 0/1 [N,H,W].
    quantile : float, optional
        The SDF scale's quantile (default 0.95).
    min_scale : float, optional
        The SDF's smallest scale (default 1e-6).
    min_distance : float, optional
        The skeleton's distance floor (default 1 px).

    Returns
    -------
    tuple of numpy.ndarray
        (sdf float32 [N,H,W], skeleton bool [N,H,W], area float64 [N]).

    Raises
    ------
    InputError
        ``masks`` is not 3-D or not binary.
    """
    masks = np.asarray(masks)
    if masks.ndim != 3:
        raise InputError(f"masks: expected [N,H,W], got shape {masks.shape}")
    if masks.dtype != bool:
        masks = np.stack([_as_mask(m, "masks") for m in masks]) if len(masks) else masks.astype(bool)
    n, h, w = masks.shape
    sdf = np.zeros((n, h, w), np.float32)
    skel = np.zeros((n, h, w), bool)
    counts = np.count_nonzero(masks.reshape(n, h * w), axis=1)  # (explicit size: -1 is ambiguous when n = 0)
    area = counts / float(h * w) if h * w else np.zeros(n)
    full = counts == h * w
    sdf[full], skel[full] = 1.0, True
    for i in np.flatnonzero((counts > 0) & ~full):
        d_in, d_out = distance_maps(masks[i])
        sdf[i] = _sdf_from_distances(d_in, d_out, quantile, min_scale)
        skel[i] = _skeleton_from_distance(masks[i], d_in, min_distance)
    return sdf, skel, area


def area_ratios(masks: np.ndarray) -> np.ndarray:
    """Compute :func:`area_ratio` of every mask of a batch.

    Parameters
    ----------
    masks : array_like
        Masks [N,H,W] (non-zero is foreground).

    Returns
    -------
    numpy.ndarray
        float64 [N].
    """
    masks = np.asarray(masks, dtype=bool)
    n, pixels = masks.shape[0], int(np.prod(masks.shape[1:]))
    return np.count_nonzero(masks.reshape(n, pixels), axis=1) / float(pixels)


def foreground_agreement(agreement: np.ndarray, voted: np.ndarray) -> float | np.ndarray:
    """Mean agreement within the voted foreground (eq:foreground-agreement).

    c = sum_x A(x) M(x) / sum_x M(x); c = 0 when M is empty.

    Parameters
    ----------
    agreement : array_like
        A, [H,W] or [N,H,W].
    voted : array_like
        M, the shape of ``agreement`` (non-zero is foreground).

    Returns
    -------
    float or numpy.ndarray
        A float for [H,W], float64 [N] for a batch.

    Raises
    ------
    InputError
        The shapes differ or are neither 2-D nor 3-D.
    """
    agreement = np.asarray(agreement)
    if agreement.dtype.kind != "f":
        agreement = agreement.astype(np.float64)
    voted = np.asarray(voted, dtype=bool)
    if agreement.shape != voted.shape:
        raise InputError(f"agreement {agreement.shape} and voted {voted.shape} shapes differ")
    if agreement.ndim not in (2, 3):
        raise InputError(f"agreement: expected [H,W] or [N,H,W], got shape {agreement.shape}")
    single = agreement.ndim == 2
    a = agreement.reshape(1 if single else agreement.shape[0], -1)
    m = voted.reshape(a.shape)
    den = np.count_nonzero(m, axis=1)
    num = (a * m).sum(axis=1, dtype=np.float64)  # float32 products are exact (m is 0/1); float64 sum
    c = np.divide(num, den, out=np.zeros(len(den)), where=den > 0)
    return float(c[0]) if single else c


def valid_ratio(n_valid, n_prompts: int = N_PROMPTS):
    """Valid-prompt ratio v = |V| / 6 (eq:valid-prompt-ratio).

    Parameters
    ----------
    n_valid : int or array_like
        |V| per image.
    n_prompts : int, optional
        The prompt-set size, the denominator (default ``geometry.n_prompts``, 6).

    Returns
    -------
    float or numpy.ndarray
        A float for a scalar, float64 otherwise.

    Raises
    ------
    InputError
        ``n_prompts`` is not positive.
    """
    if n_prompts <= 0:
        raise InputError(f"geometry.n_prompts={n_prompts!r} must be positive")
    v = np.asarray(n_valid, dtype=np.float64) / float(n_prompts)
    return float(v) if v.ndim == 0 else v


class GateFactors(NamedTuple):
    """The gate factors and the reliability gate of one image or a batch.

    Attributes
    ----------
    conf : float or numpy.ndarray
        g_conf (eq:confidence-gate).
    valid : float or numpy.ndarray
        g_valid (eq:validity-gate).
    area : float or numpy.ndarray
        g_area (eq:area-gate).
    g : float or numpy.ndarray
        g (eq:reliability-gate).
    """

    conf: float | np.ndarray
    valid: float | np.ndarray
    area: float | np.ndarray
    g: float | np.ndarray


def gate_factors(c, v, a, a0, *, conf_offset: float = CONF_OFFSET, valid_offset: float = VALID_OFFSET,
                 area_temperature: float = AREA_TEMPERATURE, area_floor: float = AREA_FLOOR,
                 eps: float = EPS) -> GateFactors:
    """Reliability gate of the pseudo-geometry losses.

    g_conf  = clip((c - 0.35) / (1 - 0.35), 0, 1)                       (eq:confidence-gate)
    g_valid = clip((v - 0.20) / (1 - 0.20), 0, 1)                       (eq:validity-gate)
    g_area  = clip(exp(-|log((a + eps) / (a0 + eps))| / 0.9), 0.05, 1)  (eq:area-gate)
    g       = clip(g_conf * g_valid * g_area, 0, 1)                     (eq:reliability-gate)

    Parameters
    ----------
    c : float or array_like
        Foreground agreement (eq:foreground-agreement).
    v : float or array_like
        Valid-prompt ratio (eq:valid-prompt-ratio).
    a : float or array_like
        Pseudo-foreground area ratio (eq:pseudo-area), >= 0.
    a0 : float or array_like
        The training median area (:func:`median_area`), >= 0.
    conf_offset : float, optional
        eq:confidence-gate's 0.35.
    valid_offset : float, optional
        eq:validity-gate's 0.20.
    area_temperature : float, optional
        eq:area-gate's 0.9.
    area_floor : float, optional
        eq:area-gate's 0.05.
    eps : float, optional
        eq:area-gate's epsilon, 1e-6.

    Returns
    -------
    GateFactors
        Floats when every input is a scalar, else arrays broadcast to a common shape.

    Raises
    ------
    InputError
        An input is NaN or infinite, or an area is negative.
    """
    arrays = [np.asarray(x, dtype=np.float64) for x in (c, v, a, a0)]
    for name, x in zip(("c", "v", "a", "a0"), arrays):
        if not np.isfinite(x).all():
            raise InputError(f"gate_factors: {name} contains NaN or infinite values")
    c_, v_, a_, a0_ = arrays
    if (a_ < 0).any() or (a0_ < 0).any():
        raise InputError("gate_factors: areas a and a0 must be non-negative")
    g_conf = np.clip((c_ - conf_offset) / (1.0 - conf_offset), 0.0, 1.0)
    g_valid = np.clip((v_ - valid_offset) / (1.0 - valid_offset), 0.0, 1.0)
    g_area = np.clip(np.exp(-np.abs(np.log((a_ + eps) / (a0_ + eps))) / area_temperature), area_floor, 1.0)
    g = np.clip(g_conf * g_valid * g_area, 0.0, 1.0)
    scalar = all(x.ndim == 0 for x in arrays)
    return GateFactors(*(float(x) if scalar else np.array(x) for x in np.broadcast_arrays(g_conf, g_valid, g_area, g)))


def median_area(a, is_train) -> float:
    """Area reference a0 = median{a_i : i in the training split, a_i > 0} (the text before eq:confidence-gate).

    Parameters
    ----------
    a : array_like
        Area ratio of every image.
    is_train : array_like
        bool, the shape of ``a``: whether the image is in the training split.

    Returns
    -------
    float
        a0.

    Raises
    ------
    InputError
        ``a`` and ``is_train`` differ in shape.
    NoForeground
        No training image has a non-empty pseudo-mask (docs/decisions.md, "The area reference a0").
    """
    a = np.asarray(a, dtype=np.float64)
    is_train = np.asarray(is_train, dtype=bool)
    if a.shape != is_train.shape:
        raise InputError(f"median_area: a {a.shape} and is_train {is_train.shape} shapes differ")
    sel = a[is_train & (a > 0)]
    if sel.size == 0:
        raise NoForeground()
    return float(np.median(sel))


#: the ``{}``: the params override, spelled for the caller
NO_FOREGROUND = ("The teacher found no spacecraft in any training image; the two likely causes: the checkpoint "
                 "is not a trained SAM 3 (random or other weights), or the teacher's scores are below "
                 "teacher.score_threshold on these images (try a lower `{}`; or check the prompts)")


class NoForeground(InputError):
    """No training image has a non-empty pseudo-mask, said in the user's terms.

    An :class:`InputError` whose message names the two likely causes and the params override to try.
    """

    def __init__(self):
        super().__init__(NO_FOREGROUND, SET(["teacher.score_threshold=…"]))

    def __reduce__(self):  # pickles (a worker process) as itself: its message takes no arguments
        """Pickle as itself (for worker processes): the message takes no arguments."""
        return (NoForeground, ())


def image_gates(c, n_valid, a, a0, geo) -> tuple[np.ndarray, GateFactors]:
    """Compute v and the gate factors of images at a given reference area.

    eq:valid-prompt-ratio, then eq:confidence-gate .. eq:reliability-gate with the params' constants.

    Parameters
    ----------
    c : float or array_like
        Foreground agreement.
    n_valid : int or array_like
        |V| per image.
    a : float or array_like
        Area ratio per image.
    a0 : float
        The area reference (:func:`median_area`).
    geo : mapping
        The params ``geometry`` section.

    Returns
    -------
    tuple
        (v, :class:`GateFactors`).
    """
    v = valid_ratio(n_valid, geo["n_prompts"])
    return v, gate_factors(c, v, a, a0, conf_offset=geo["conf_offset"], valid_offset=geo["valid_offset"],
                           area_temperature=geo["area_temperature"], area_floor=geo["area_floor"], eps=geo["eps"])
