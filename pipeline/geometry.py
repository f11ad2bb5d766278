"""Pseudo-geometry targets and the reliability gate (paper, section "Reliability-Aware Pseudo-Geometry
Refinement": eq:sdf-target, skeleton, eq:pseudo-area, eq:foreground-agreement .. eq:reliability-gate).

All targets derive from the voted pseudo-mask M = M_i^T of :mod:`pipeline.consensus`.

Distance convention (eq:sdf-target)
    d_in(x)  = Euclidean distance from a foreground pixel x to the nearest *background* pixel
               (0 on background); d_out(x) = Euclidean distance from a background pixel x to the
               nearest *foreground* pixel (0 on foreground).  Distances are between pixel centres, in
               pixels, computed exactly by OpenCV (``cv2.distanceTransform(..., cv2.DIST_L2,
               cv2.DIST_MASK_PRECISE)``; squared distances rounded back to their exact integers
               before the square root, see :func:`squared_distance`).  Hence D~ = d_in - d_out is >= 1 on M and <= -1 off M:
               the sign of D~ (and of D) always agrees with M and no pixel has D~ = 0.
    The image border is NOT background: pixels outside the frame do not exist, so a mask touching
    the border gets its d_in from the real background pixels inside the frame only (a spacecraft cut
    by the frame is not thinner than it looks).  OpenCV's precise transform already behaves this way
    (verified in tests/test_geometry.py against scipy's ``distance_transform_edt``, which has the
    same semantics), so no padding is needed.

Skeleton ("Skel" in the text after eq:sdf-target)
    K = {x : d_in(x) > t  and  d_in(x) >= max_{y in N8(x)} d_in(y)} with t = 1 px, i.e. the
    non-strict local maxima of d_in over the 3x3 neighbourhood (the pixel itself and its 8
    neighbours; neighbours outside the frame are ignored), after removing points whose distance
    does not exceed one pixel.  Non-strict so that the two-pixel-wide ridges of even-width bars
    are kept.  A non-empty M with an empty K falls back to K = M: this happens when every pixel of
    M lies within 1 px of the background (d_in = 1 everywhere on 1- and 2-px thick structures), and
    for a full frame (no background, d_in undefined).  K is always inside M.

Gate constants are keyword arguments whose defaults are the paper's values from the params schema
(``pipeline.params.PAPER.geometry``); params.yaml ``geometry:`` holds the values a run uses.
"""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from pipeline.runtime.errors import SET, InputError

from pipeline.params import PAPER

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


def _cv2():
    import cv2

    return cv2


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
    """Exact squared Euclidean distance (float32, integer-valued) from every non-zero pixel of the
    uint8 image ``nonzero`` to its nearest zero pixel; 0 on zero pixels.  Pixels outside the frame
    do not exist (the frame is not a zero pixel).

    OpenCV's DIST_MASK_PRECISE transform is exact in squared distance, but its final square root
    differs by one float32 ulp between calls (it depends on the buffer's alignment); rounding the
    square back to its integer makes results bit-for-bit deterministic.  Exact while d^2 < 2^22.
    """
    cv2 = _cv2()
    d = cv2.distanceTransform(np.ascontiguousarray(nonzero, dtype=np.uint8), cv2.DIST_L2, cv2.DIST_MASK_PRECISE)
    np.multiply(d, d, out=d)
    return np.rint(d, out=d)


def exact_distance(nonzero: np.ndarray) -> np.ndarray:
    """sqrt of :func:`squared_distance`: exact, deterministic Euclidean distances (float32, pixels)."""
    return np.sqrt(squared_distance(nonzero))


def distance_maps(mask: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """(d_in, d_out) float32 [H,W]: exact Euclidean distances (pixels) to the nearest pixel of the
    other set; see the module docstring.  Only meaningful when M is neither empty nor full (OpenCV
    returns ~1.8e19 where the other set is empty)."""
    m8 = np.ascontiguousarray(mask, dtype=np.uint8)
    return exact_distance(m8), exact_distance(1 - m8)


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
    """Normalised signed distance target D (eq:sdf-target), float32 [H,W] in [-1, 1].

    D~ = d_in - d_out (module docstring: exact Euclidean distances to the nearest pixel of the other
    set, pixel centres, image border not background); s = q_0.95(|D~|) over all H*W pixels (numpy's
    linear interpolation) when s >= 1e-6, else s = 1; D = clip(D~ / s, -1, 1).
    Edge cases: empty M -> 0 everywhere; full M -> 1 everywhere.  sign(D) agrees with M.
    With pixel-centre distances |D~| >= 1 on every pixel of a non-degenerate mask, so q >= 1 and the
    paper's s = 1 fallback (q < 1e-6) is kept for fidelity but only reachable through ``min_scale``.
    """
    mask = _as_mask(mask)
    if not mask.any():
        return np.zeros(mask.shape, np.float32)
    if mask.all():
        return np.ones(mask.shape, np.float32)
    return _sdf_from_distances(*distance_maps(mask), quantile, min_scale)


def _skeleton_from_distance(mask: np.ndarray, d_in: np.ndarray, min_distance: float) -> np.ndarray:
    cv2 = _cv2()
    # 3x3 grey dilation = max over the 8-neighbourhood and the pixel; OpenCV's default border for
    # dilation is the minimum value, so pixels outside the frame never win the comparison.
    neighbourhood_max = cv2.dilate(d_in, np.ones((3, 3), np.uint8))
    skel = (d_in > min_distance) & (d_in >= neighbourhood_max)
    if not skel.any():
        return mask.copy()  # a non-empty mask with no valid skeleton falls back to M
    return skel


def skeleton_target(mask: np.ndarray, *, min_distance: float = SKELETON_MIN_DISTANCE) -> np.ndarray:
    """Skeleton target K (text after eq:sdf-target), bool [H,W].

    K = non-strict 3x3 local maxima of d_in with d_in > ``min_distance`` (1 px); see the module
    docstring for the exact definition.  Empty M -> empty K; a non-empty M without such maxima
    (every pixel within 1 px of the background, e.g. lines 1-2 px thick) -> K = M.
    Full M: d_in is undefined (no background); we take K = M (no finite interior maxima exist, and
    the fallback rule applies).  K is always a subset of M.
    """
    mask = _as_mask(mask)
    if not mask.any():
        return np.zeros(mask.shape, bool)
    if mask.all():
        return mask.copy()
    return _skeleton_from_distance(mask, exact_distance(mask.view(np.uint8)), min_distance)


def area_ratio(mask: np.ndarray) -> float:
    """Pseudo-foreground area ratio a = (1/HW) sum_x M(x) (eq:pseudo-area), in [0, 1]."""
    mask = _as_mask(mask)
    return float(np.count_nonzero(mask)) / mask.size if mask.size else 0.0


def pseudo_targets(masks: np.ndarray, *, quantile: float = SDF_QUANTILE, min_scale: float = SDF_MIN_SCALE,
                   min_distance: float = SKELETON_MIN_DISTANCE) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """SDF, skeleton and area of a batch of voted masks bool [N,H,W] in one pass (the distance
    transforms are shared between SDF and skeleton).

    Returns (sdf float32 [N,H,W], skeleton bool [N,H,W], area float64 [N]); identical to calling
    :func:`sdf_target`, :func:`skeleton_target` and :func:`area_ratio` per image.
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
    for i in range(n):
        m = masks[i]
        if counts[i] == 0:
            continue
        if counts[i] == h * w:
            sdf[i] = 1.0
            skel[i] = True
            continue
        d_in, d_out = distance_maps(m)
        sdf[i] = _sdf_from_distances(d_in, d_out, quantile, min_scale)
        skel[i] = _skeleton_from_distance(m, d_in, min_distance)
    return sdf, skel, area


def area_ratios(masks: np.ndarray) -> np.ndarray:
    """Vectorised :func:`area_ratio` over bool [N,H,W] -> float64 [N]."""
    masks = np.asarray(masks, dtype=bool)
    n, pixels = masks.shape[0], int(np.prod(masks.shape[1:]))
    return np.count_nonzero(masks.reshape(n, pixels), axis=1) / float(pixels)


def foreground_agreement(agreement: np.ndarray, voted: np.ndarray) -> float | np.ndarray:
    """c = sum_x A(x) M(x) / sum_x M(x), 0 when M is empty (eq:foreground-agreement).

    ``agreement`` float [H,W] and ``voted`` bool [H,W] -> float; or [N,H,W] each -> float64 [N].
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
    """v = |V| / 6 (eq:valid-prompt-ratio); the denominator is the prompt-set size ``n_prompts``."""
    if n_prompts <= 0:
        raise InputError(f"geometry.n_prompts={n_prompts!r} must be positive")
    v = np.asarray(n_valid, dtype=np.float64) / float(n_prompts)
    return float(v) if v.ndim == 0 else v


class GateFactors(NamedTuple):
    """Gate factors (eq:confidence-gate, eq:validity-gate, eq:area-gate) and their product g
    (eq:reliability-gate); floats for scalar inputs, float64 arrays for array inputs."""

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

    c, v, a, a0: scalars or broadcastable arrays (c, v, a in [0, 1]; a0 the training median area).
    No valid prompt (v = 0) gives g_valid = 0 hence g = 0; an empty pseudo-mask has c = 0 hence g = 0.
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
    out = np.broadcast_arrays(g_conf, g_valid, g_area, g)
    if all(x.ndim == 0 for x in arrays):
        return GateFactors(*(float(x) for x in out))
    return GateFactors(*(np.array(x) for x in out))


def median_area(a, is_train) -> float:
    """a0 = median of a_i over NON-EMPTY TRAINING pseudo-masks (text before eq:confidence-gate).

    ``a`` float [N] pseudo-area ratios, ``is_train`` bool [N].  Numpy's median (mean of the two
    middle values for an even count).  Decision for the degenerate case: when no training image has
    a non-empty pseudo-mask there is no reference area, and any fallback would silently change what
    the area gate means, so this raises :class:`NoForeground`, an InputError in the user's terms (the
    teacher produced nothing usable to train on).
    """
    a = np.asarray(a, dtype=np.float64)
    is_train = np.asarray(is_train, dtype=bool)
    if a.shape != is_train.shape:
        raise InputError(f"median_area: a {a.shape} and is_train {is_train.shape} shapes differ")
    sel = a[is_train & (a > 0)]
    if sel.size == 0:
        raise NoForeground()
    return float(np.median(sel))


#: what label's summary and distill's error say when every pseudo-mask is empty, with the two likely
#: causes (the ``{}``: the params override, spelled for the caller)
NO_FOREGROUND = ("The teacher found no spacecraft in any training image; the two likely causes: the checkpoint "
                 "is not a trained SAM 3 (random or other weights), or the teacher's scores are below "
                 "teacher.score_threshold on these images (try a lower `{}`; or check the prompts)")


class NoForeground(InputError):
    """No training image has a non-empty pseudo-mask (:func:`median_area`): said in the user's terms --
    no file, no equation (:data:`NO_FOREGROUND`); the params override is spelled for the caller (``--set
    ...`` on the command line, ``overrides=[...]`` in Python: :class:`pipeline.runtime.errors.Option`)."""

    def __init__(self):
        super().__init__(NO_FOREGROUND, SET(["teacher.score_threshold=…"]))

    def __reduce__(self):  # pickles (a worker process) as itself: its message takes no arguments
        return (NoForeground, ())


def image_gates(c, n_valid, a, a0, geo) -> tuple[np.ndarray, GateFactors]:
    """(v, :class:`GateFactors`) of images with agreement ``c``, valid-prompt counts ``n_valid`` and
    areas ``a`` against the reference area ``a0`` (eq:valid-prompt-ratio, eq:confidence-gate ..
    eq:reliability-gate) with the constants of the params ``geometry`` section ``geo``: the gate of the
    geometry stage and of ``geodistill label``."""
    v = valid_ratio(n_valid, geo["n_prompts"])
    return v, gate_factors(c, v, a, a0, conf_offset=geo["conf_offset"], valid_offset=geo["valid_offset"],
                           area_temperature=geo["area_temperature"], area_floor=geo["area_floor"], eps=geo["eps"])
