"""A SIMULATOR of a six-prompt foundation teacher's errors (eq:teacher-prediction), for the synthetic benchmark only.

It degrades the synthetic ground truth, one persona per prompt (docs/decisions.md, "The simulated teacher").
"""

from __future__ import annotations

import dataclasses
import hashlib
import logging
from typing import Any, Mapping, Sequence

import numpy as np

from pipeline.runtime.errors import InputError
from pipeline.metrics import image_iou
from pipeline.params import PAPER
from pipeline.teacher_table import SIMULATED as BACKEND
from pipeline.teachers.base import RegisteredTeacher, TeacherInput, finalize_answers

__all__ = ["SIMULATOR_VERSION", "BUS", "PANEL", "THIN", "DISH", "PAYLOAD", "MODES", "Persona", "PERSONAS",
           "HARD_CASE_MODES", "GENERIC_PERSONA", "SimulatorConfig", "dilate", "erode", "open_mask", "drop_thin",
           "bus_only", "bright_region", "glare_blob", "scale_difficulty", "scene_difficulty", "SceneDraw", "MISS",
           "PromptDraw", "SimulatedFoundationTeacher", "persona_for"]

log = logging.getLogger(__name__)

#: the simulator's version, in its fingerprint: a change of its draws or constants gets a new one
SIMULATOR_VERSION = 1

#: parts codes of reference.zarr ``parts``
BUS, PANEL, THIN, DISH, PAYLOAD = 1, 2, 3, 4, 5

#: the failure modes of an answer (``clean``: the ground truth itself)
MODES = ("clean", "dilate", "erode", "drop_thin", "bus_only", "false_positive", "wrong_object")


@dataclasses.dataclass(frozen=True)
class Persona:
    """Failure profile of one prompt.

    Attributes
    ----------
    name : str
        The persona's name.
    miss : float
        P(miss) on an easy image: P(miss) = ``miss + miss_slope * d``, d the scene difficulty.
    miss_slope : float
        P(miss)'s increase per unit difficulty.
    modes : Mapping
        Weights of the failure modes (:data:`MODES`) on an easy image.
    hard_modes : Mapping
        Weight added to each mode per unit difficulty.
    boundary_frac : float
        Boundary bias of dilate/erode as a fraction of the object's equivalent radius.
    survivor : float
        P(still answers in a breakdown).
    shares : float
        P(takes part in an image's shared error).
    score_bias : float
        Added to the answer's score.
    """

    name: str
    miss: float
    miss_slope: float
    modes: Mapping[str, float]
    hard_modes: Mapping[str, float]
    boundary_frac: float = 0.10
    survivor: float = 0.1
    shares: float = 0.7
    score_bias: float = 0.0


def _m(**kw) -> dict[str, float]:
    """Return a weight for every mode of :data:`MODES`, 0 where ``kw`` gives none."""
    return {m: float(kw.get(m, 0.0)) for m in MODES}


#: one persona per prompt of eq:prompt-set: the category-level prompts are the least specific, the
#: structural ones describe the full silhouette best
PERSONAS: dict[str, Persona] = {
    "spacecraft": Persona(
        "spacecraft", miss=0.06, miss_slope=0.15,
        modes=_m(clean=4.0, dilate=1.0, erode=1.0, drop_thin=1.0, bus_only=0.6, false_positive=0.6, wrong_object=0.5),
        hard_modes=_m(drop_thin=1.5, bus_only=1.0, wrong_object=1.0, false_positive=0.5), survivor=0.2),
    "satellite": Persona(
        "satellite", miss=0.50, miss_slope=0.30,
        modes=_m(clean=1.0, dilate=0.8, erode=0.8, drop_thin=1.0, bus_only=1.2, false_positive=0.6, wrong_object=1.6),
        hard_modes=_m(bus_only=1.0, wrong_object=2.0), survivor=0.06),
    "space probe": Persona(
        "space probe", miss=0.82, miss_slope=0.15,
        modes=_m(clean=0.3, dilate=0.3, erode=0.3, drop_thin=0.6, bus_only=1.0, false_positive=0.3, wrong_object=2.5),
        hard_modes=_m(wrong_object=2.0), survivor=0.03),
    "space vehicle": Persona(
        "space vehicle", miss=0.25, miss_slope=0.35,
        modes=_m(clean=2.5, dilate=0.8, erode=1.0, drop_thin=1.2, bus_only=0.8, false_positive=0.5, wrong_object=0.8),
        hard_modes=_m(drop_thin=1.5, wrong_object=1.2), survivor=0.08),
    "spacecraft with rigid body and appendages": Persona(
        "rigid body and appendages", miss=0.02, miss_slope=0.10,
        modes=_m(clean=8.0, dilate=1.0, erode=0.8, drop_thin=0.5, bus_only=0.3, false_positive=0.4, wrong_object=0.2),
        hard_modes=_m(drop_thin=1.0, erode=0.5, wrong_object=0.5), survivor=0.2),
    "artificial object in space with panels and antennas": Persona(
        "panels and antennas", miss=0.04, miss_slope=0.15,
        modes=_m(clean=6.0, dilate=1.5, erode=0.5, drop_thin=0.4, bus_only=0.2, false_positive=1.5, wrong_object=0.5),
        hard_modes=_m(false_positive=1.5, wrong_object=0.8, drop_thin=0.5), survivor=0.12),
}
#: scene hard cases of the synthetic benchmark that favour particular failure modes (added weights)
HARD_CASE_MODES: dict[str, dict[str, float]] = {
    "glare": {"false_positive": 1.5, "wrong_object": 0.5},
    "flare": {"false_positive": 1.5, "wrong_object": 0.5},
    "underexposed": {"erode": 1.0, "drop_thin": 1.0, "bus_only": 0.5},
    "blur": {"dilate": 1.0, "drop_thin": 0.5},
    "noise": {"dilate": 0.5, "erode": 0.5},
}

#: the persona of a prompt outside eq:prompt-set
GENERIC_PERSONA = Persona(
    "generic", miss=0.25, miss_slope=0.35,
    modes=_m(clean=2.0, dilate=1.0, erode=1.0, drop_thin=1.0, bus_only=0.8, false_positive=0.8, wrong_object=1.0),
    hard_modes=_m(drop_thin=1.5, wrong_object=1.5), survivor=0.08)


@dataclasses.dataclass(frozen=True)
class SimulatorConfig:
    """Image-level constants of the simulator (part of its fingerprint through :data:`SIMULATOR_VERSION`).

    The scene difficulty is d = clip(w_scale * scale + w_hard_case * hard case + w_bright_background * bright
    background + w_noise * (noise - 0.5), 0, 1) (:func:`scene_difficulty`).

    Attributes
    ----------
    easy_area : float
        Area fraction at and above which scale adds no difficulty.
    hard_area : float
        Area fraction at and below which the scale difficulty is 1.
    w_scale : float
        d's weight of the scale difficulty.
    w_hard_case : float
        d's weight of a hard case.
    w_bright_background : float
        d's weight of a bright background (Earth, limb, planet, moon, cloud).
    w_noise : float
        d's weight of the image's uniform noise draw, centred.
    breakdown_base : float
        P(breakdown) = base + slope * d (clipped to [0, 0.95]).
    breakdown_slope : float
        See ``breakdown_base``.
    shared_thin_base : float
        P(shared thin-structure loss) = base + slope * scale difficulty.
    shared_thin_slope : float
        See ``shared_thin_base``.
    shared_fp_base : float
        P(shared glare / Earth-limb region) = base + slope * d.
    shared_fp_slope : float
        See ``shared_fp_base``.
    """

    easy_area: float = 0.10          # area fraction at and above which scale adds no difficulty
    hard_area: float = 0.004         # area fraction at and below which scale difficulty is 1
    w_scale: float = 0.55
    w_hard_case: float = 0.35
    w_bright_background: float = 0.15
    w_noise: float = 0.25
    breakdown_base: float = 0.04     # P(breakdown) = base + slope * d  (clipped to [0, 0.95])
    breakdown_slope: float = 0.60
    shared_thin_base: float = 0.05   # P(shared thin-structure loss) = base + slope * scale difficulty
    shared_thin_slope: float = 0.35
    shared_fp_base: float = 0.05     # P(shared glare / Earth-limb region) = base + slope * d
    shared_fp_slope: float = 0.25


def _rng(*parts: Any) -> np.random.Generator:
    """Return a numpy Generator seeded by sha256 over the string forms of ``parts``."""
    h = hashlib.sha256("\x1f".join(str(p) for p in parts).encode()).digest()
    return np.random.Generator(np.random.PCG64(int.from_bytes(h[:16], "little")))


def _morph(op: str, mask: np.ndarray, radius: int) -> np.ndarray:
    """Apply cv2's ``op`` with an elliptical element of ``radius`` px (radius 0: a copy)."""
    import cv2

    if radius <= 0:
        return mask.copy()
    r = max(int(radius), 1)
    disk = cv2.getStructuringElement(cv2.MORPH_ELLIPSE, (2 * r + 1, 2 * r + 1))
    return getattr(cv2, op)(mask.astype(np.uint8), disk).astype(bool)


def dilate(mask: np.ndarray, radius: int) -> np.ndarray:
    """Push the boundary outwards by ``radius`` px (elliptical structuring element).

    Parameters
    ----------
    mask : numpy.ndarray
        bool [H,W].
    radius : int
        Pixels; 0: the identity.

    Returns
    -------
    numpy.ndarray
        bool [H,W].
    """
    return _morph("dilate", mask, radius)


def erode(mask: np.ndarray, radius: int) -> np.ndarray:
    """Pull the boundary inwards by ``radius`` px (elliptical structuring element).

    Parameters
    ----------
    mask : numpy.ndarray
        bool [H,W].
    radius : int
        Pixels; 0: the identity.

    Returns
    -------
    numpy.ndarray
        bool [H,W].
    """
    return _morph("erode", mask, radius)


def open_mask(mask: np.ndarray, radius: int) -> np.ndarray:
    """Open the mask morphologically: remove structures thinner than about 2 * radius px.

    Parameters
    ----------
    mask : numpy.ndarray
        bool [H,W].
    radius : int
        Pixels.

    Returns
    -------
    numpy.ndarray
        bool [H,W], within ``mask``.
    """
    return dilate(erode(mask, radius), radius) & mask


def drop_thin(mask: np.ndarray, parts: np.ndarray | None, radius: int, drop_dish: bool) -> np.ndarray:
    """Remove thin appendages: booms and, with ``drop_dish``, dishes.

    Parameters
    ----------
    mask : numpy.ndarray
        bool [H,W].
    parts : numpy.ndarray or None
        The parts codes [H,W] (:data:`THIN`, :data:`DISH`, ...); without thin parts (or None), an opening of
        ``radius`` px instead.
    radius : int
        The opening's radius.
    drop_dish : bool
        Remove dishes too.

    Returns
    -------
    numpy.ndarray
        bool [H,W]; ``mask`` itself (a copy) when nothing would be left.
    """
    if parts is not None and (parts == THIN).any():
        out = mask & ~np.isin(parts, (THIN, DISH) if drop_dish else (THIN,))
    else:
        out = open_mask(mask, radius)
    return out if out.any() else mask.copy()


def bus_only(mask: np.ndarray, parts: np.ndarray | None) -> np.ndarray:
    """Keep only the spacecraft bus (and payload).

    Parameters
    ----------
    mask : numpy.ndarray
        bool [H,W].
    parts : numpy.ndarray or None
        The parts codes [H,W]; without (or with no bus), a strong opening keeps the compact core.

    Returns
    -------
    numpy.ndarray
        bool [H,W].
    """
    if parts is not None:
        core = mask & np.isin(parts, (BUS, PAYLOAD))
        if core.any():
            return core
    n = np.count_nonzero(mask)
    radius = max(2, int(0.25 * np.sqrt(n / np.pi)))
    core = open_mask(mask, radius)
    return core if core.any() else erode(mask, 1)


def bright_region(image: np.ndarray, exclude: np.ndarray, min_fraction: float = 0.01) -> np.ndarray:
    """Find the largest bright region outside ``exclude``: the Earth limb or a glare patch.

    Parameters
    ----------
    image : numpy.ndarray
        uint8 [H,W,3].
    exclude : numpy.ndarray
        bool [H,W]: where the region may not lie.
    min_fraction : float, optional
        The smallest share of the frame it may cover.

    Returns
    -------
    numpy.ndarray
        bool [H,W]: the largest 8-connected region with luminance >= max(120, its 90th percentile outside
        ``exclude``); empty when it covers less than ``min_fraction`` of the frame.
    """
    import cv2

    lum = image.astype(np.float32).mean(axis=-1)
    outside = ~exclude
    if not outside.any():
        return np.zeros_like(exclude)
    thr = max(120.0, float(np.percentile(lum[outside], 90)))
    bright = (lum >= thr) & outside
    n, labels, stats, _ = cv2.connectedComponentsWithStats(bright.astype(np.uint8), connectivity=8)
    if n <= 1:
        return np.zeros_like(exclude)
    k = 1 + int(np.argmax(stats[1:, cv2.CC_STAT_AREA]))
    region = labels == k
    return region if region.mean() >= min_fraction else np.zeros_like(exclude)


def glare_blob(mask: np.ndarray, rng: np.random.Generator, attached: bool) -> np.ndarray:
    """Draw an elliptical glare blob.

    Parameters
    ----------
    mask : numpy.ndarray
        bool [H,W]: the object.
    rng : numpy.random.Generator
        The draws.
    attached : bool
        The blob touches the object's boundary (a flare on the hull); otherwise it lies elsewhere in the frame
        (a reflection or star-tracker ghost).

    Returns
    -------
    numpy.ndarray
        bool [H,W].
    """
    h, w = mask.shape
    n = max(np.count_nonzero(mask), 1)
    r_obj = np.sqrt(n / np.pi)
    ys, xs = np.nonzero(mask) if mask.any() else (np.array([h // 2]), np.array([w // 2]))
    if attached:
        j = rng.integers(len(ys))
        cy, cx = ys[j], xs[j]
        ry, rx = r_obj * rng.uniform(0.3, 0.7, size=2)
    else:
        for _ in range(20):
            cy, cx = rng.uniform(0.1, 0.9) * h, rng.uniform(0.1, 0.9) * w
            if np.hypot(cy - ys.mean(), cx - xs.mean()) > 1.5 * r_obj + 0.1 * h:
                break
        ry, rx = max(r_obj, 0.04 * h) * rng.uniform(0.4, 0.9, size=2)
    yy, xx = np.ogrid[:h, :w]
    return ((yy - cy) / max(ry, 1.0)) ** 2 + ((xx - cx) / max(rx, 1.0)) ** 2 <= 1.0


def _truthy(x: Any) -> bool:
    """Read a manifest flag: empty, 0, false, no, none, nan and NaN are False."""
    if isinstance(x, str):
        return x.strip().lower() not in ("", "0", "false", "no", "none", "nan")
    try:
        return x is not None and bool(x) and not (isinstance(x, float) and np.isnan(x))
    except (TypeError, ValueError):
        return False


def scale_difficulty(area_fraction: float, cfg: SimulatorConfig = SimulatorConfig()) -> float:
    """Rate how hard a target's size makes it.

    Parameters
    ----------
    area_fraction : float
        The share of the frame the target covers.
    cfg : SimulatorConfig, optional
        The constants (``easy_area``, ``hard_area``).

    Returns
    -------
    float
        0 for targets covering >= ``easy_area`` of the frame, 1 at <= ``hard_area``, log-linear between.
    """
    a = max(float(area_fraction), 1e-8)
    t = (np.log(cfg.easy_area) - np.log(a)) / (np.log(cfg.easy_area) - np.log(cfg.hard_area))
    return float(np.clip(t, 0.0, 1.0))


def scene_difficulty(area_fraction: float, hard_case: bool, bright_background: bool, noise: float,
                     cfg: SimulatorConfig = SimulatorConfig()) -> float:
    """Rate an image's difficulty d for the simulated teacher.

    d = clip(w_scale * scale + w_hard_case * hard_case + w_bright_background * bright_background
    + w_noise * (noise - 0.5), 0, 1), scale = :func:`scale_difficulty`.

    Parameters
    ----------
    area_fraction : float
        The share of the frame the target covers.
    hard_case : bool
        The scene is a hard case.
    bright_background : bool
        The background is bright (Earth, limb, ...).
    noise : float
        A uniform draw in [0, 1).
    cfg : SimulatorConfig, optional
        The weights.

    Returns
    -------
    float
        d in [0, 1].
    """
    d = (cfg.w_scale * scale_difficulty(area_fraction, cfg) + cfg.w_hard_case * float(hard_case)
         + cfg.w_bright_background * float(bright_background) + cfg.w_noise * (noise - 0.5))
    return float(np.clip(d, 0.0, 1.0))


@dataclasses.dataclass
class SceneDraw:
    """Image-level draws, shared by all prompts (and both views) of one image.

    Attributes
    ----------
    difficulty : float
        d (:func:`scene_difficulty`).
    scale : float
        The scale difficulty (:func:`scale_difficulty`).
    breakdown : bool
        The teacher breaks down on this image: most prompts miss.
    shared_thin : bool
        Thin structures are lost by several prompts.
    shared_fp : bool
        One glare / Earth-limb region is included by several prompts.
    shared_fp_seed : int
        Seeds the shared glare blob.
    """

    difficulty: float
    scale: float
    breakdown: bool
    shared_thin: bool      # thin structures lost by several prompts
    shared_fp: bool        # one glare / Earth-limb region included by several prompts
    shared_fp_seed: int


#: :attr:`PromptDraw.mode` of a prompt that gave no answer (it missed, or did not survive a breakdown)
MISS = "miss"


@dataclasses.dataclass(frozen=True)
class PromptDraw:
    """What the SIMULATOR drew for one (image, prompt) answer, beside the answer itself.

    An answered mode may still end empty (score 0).

    Attributes
    ----------
    mode : str
        One of :data:`MODES`, or :data:`MISS`.
    radius : int
        The dilate/erode radius in px (drawn for every answered mode, used by ``dilate`` and ``erode`` only).
    shared_thin : bool
        This answer took part in the image's shared thin-structure loss (:class:`SceneDraw`).
    shared_fp : bool
        This answer took part in the image's shared glare region (:class:`SceneDraw`).
    jitter : int
        The independent boundary jitter in px (> 0 dilates, < 0 erodes, 0 none).
    """

    mode: str
    radius: int = 0
    shared_thin: bool = False
    shared_fp: bool = False
    jitter: int = 0


class SimulatedFoundationTeacher(RegisteredTeacher):
    """SIMULATOR of a six-prompt foundation teacher: answers from the synthetic ground truth, degraded.

    Its answers need each image's reference mask (:attr:`pipeline.teachers.base.TeacherInput.reference`): it is
    never a real teacher, and its numbers are labelled SIMULATOR.

    Parameters
    ----------
    seed : int, optional
        ``teacher.seed``: seeds every draw (with the image's sha256, the prompt and :data:`SIMULATOR_VERSION`).
    resolution : tuple of int, optional
        (H, W) of the working resolution, recorded in the fingerprint.
    config : SimulatorConfig, optional
        The image-level constants.
    """

    backend = BACKEND

    @classmethod
    def from_params(cls, cfg, resolution: tuple[int, int], device: str = "auto") -> "SimulatedFoundationTeacher":
        """Build the SIMULATOR of a validated ``teacher:`` section.

        Parameters
        ----------
        cfg : Mapping
            The validated ``teacher:`` section: its ``seed`` is read.
        resolution : tuple of int
            (H, W) of the working resolution.
        device : str, optional
            Unused: it runs on the CPU.

        Returns
        -------
        SimulatedFoundationTeacher
            The SIMULATOR.
        """
        return cls(seed=cfg["seed"], resolution=resolution)

    def __init__(self, seed: int = PAPER.teacher.seed, resolution: tuple[int, int] | None = None,
                 config: SimulatorConfig = SimulatorConfig()):
        self.seed = int(seed)
        self.resolution = tuple(resolution) if resolution is not None else None
        self.config = config

    def fingerprint(self) -> dict:
        """Describe what determines the answers (:meth:`pipeline.teachers.base.Teacher.fingerprint`).

        Returns
        -------
        dict
            The backend, ``simulator: True``, :data:`SIMULATOR_VERSION`, the seed and the resolution.
        """
        return {"backend": BACKEND, "simulator": True, "simulator_version": SIMULATOR_VERSION,
                "seed": self.seed, "resolution": list(self.resolution) if self.resolution else None}

    def scene(self, item: TeacherInput) -> SceneDraw:
        """Draw an image's scene: its difficulty and the errors its prompts share.

        Parameters
        ----------
        item : TeacherInput
            The image, with its reference mask and extras (``area_fraction``, ``hard_case``, ``background``).

        Returns
        -------
        SceneDraw
            The draws, seeded by the image's sha256 and the seed (the same in both views).
        """
        cfg = self.config
        gt = np.asarray(item.reference["mask"], dtype=bool)
        ex = item.extras or {}
        af = ex.get("area_fraction")
        if af is None or not np.isfinite(float(af)):
            af = float(gt.mean())
        bg = str(ex.get("background", "") or "").lower()
        bright_bg = any(s in bg for s in ("earth", "limb", "planet", "moon", "cloud"))
        rng = _rng("scene", item.image_sha256, self.seed, SIMULATOR_VERSION)
        noise = rng.random()
        scale = scale_difficulty(af, cfg)
        d = scene_difficulty(af, _truthy(ex.get("hard_case")), bright_bg, noise, cfg)
        breakdown = rng.random() < np.clip(cfg.breakdown_base + cfg.breakdown_slope * d, 0.0, 0.95)
        shared_thin = rng.random() < cfg.shared_thin_base + cfg.shared_thin_slope * scale
        shared_fp = rng.random() < cfg.shared_fp_base + cfg.shared_fp_slope * d
        return SceneDraw(d, scale, bool(breakdown), bool(shared_thin), bool(shared_fp), int(rng.integers(2**31)))

    def _prompt_draw(self, item: TeacherInput, prompt: str, what: str) -> float:
        """Draw a view-independent uniform number for (image, prompt): other prompts never change this one's."""
        return float(_rng(what, item.image_sha256, prompt, self.seed, SIMULATOR_VERSION).random())

    def answer_with_draw(self, item: TeacherInput, prompt: str, scene: SceneDraw
                         ) -> tuple[np.ndarray, float, PromptDraw]:
        """Answer one prompt for one image, and say what was drawn.

        Parameters
        ----------
        item : TeacherInput
            The image in its view, with its reference mask (and optional parts).
        prompt : str
            The prompt (its persona: :func:`persona_for`).
        scene : SceneDraw
            The image's scene draws (:meth:`scene`).

        Returns
        -------
        tuple of (numpy.ndarray, float, PromptDraw)
            The mask bool [H,W], the score (0 and an empty mask for a miss) and what it drew.
        """
        gt = np.asarray(item.reference["mask"], dtype=bool)
        parts = item.reference.get("parts")
        parts = None if parts is None else np.asarray(parts)
        empty = np.zeros_like(gt)
        persona = persona_for(prompt)
        rng = _rng("prompt", item.image_sha256, prompt, self.seed, item.view, SIMULATOR_VERSION)
        px = max(gt.shape) / 128.0  # thin structures are ~1-2 px wide at 128 px
        r_eq = float(np.sqrt(np.count_nonzero(gt) / np.pi))
        hard = str((item.extras or {}).get("hard_case", "") or "").lower()
        d = scene.difficulty
        if scene.breakdown:
            if self._prompt_draw(item, prompt, "survive") >= persona.survivor:
                return empty, 0.0, PromptDraw(MISS)
            mode = rng.choice(["bus_only", "wrong_object", "drop_thin", "false_positive", "erode"],
                              p=[0.25, 0.25, 0.20, 0.15, 0.15])
            boundary = 2.0 * persona.boundary_frac
        else:
            if rng.random() < np.clip(persona.miss + persona.miss_slope * d, 0.0, 0.98):
                return empty, 0.0, PromptDraw(MISS)
            extra = HARD_CASE_MODES.get(hard, {})
            w = np.array([persona.modes[m] + d * persona.hard_modes[m] + extra.get(m, 0.0) for m in MODES])
            mode = MODES[int(rng.choice(len(MODES), p=w / w.sum()))]
            boundary = persona.boundary_frac
        r_float = boundary * r_eq * rng.uniform(0.6, 1.4)
        r = int(np.floor(r_float + rng.random()))  # stochastic rounding: E[r] = r_float
        mask = self._apply(mode, gt, parts, item.image, rng, r, scene)
        thin = fp = False
        j = 0
        if not scene.breakdown:
            if (scene.shared_thin and mode != "wrong_object"
                    and self._prompt_draw(item, prompt, "shared_thin") < persona.shares):
                thin = True
                mask = drop_thin(mask, parts, max(1, int(round(px))), drop_dish=scene.scale > 0.5)
            if scene.shared_fp and self._prompt_draw(item, prompt, "shared_fp") < persona.shares:
                fp = True
                region = bright_region(item.image, dilate(gt, 1))
                if not region.any():
                    region = glare_blob(gt, np.random.default_rng(scene.shared_fp_seed), attached=True)
                mask = mask | region
            # small independent boundary jitter on objects large enough to have a few-pixel contour
            # uncertainty: no two prompts trace the same contour
            j = int(rng.choice([-1, 0, 1], p=[0.15, 0.7, 0.15])) if r_eq >= 16 * px else 0
            mask = dilate(mask, j) if j > 0 else erode(mask, -j) if j < 0 else mask
        draw = PromptDraw(str(mode), r, thin, fp, j)
        if not mask.any():
            return empty, 0.0, draw
        q = image_iou(mask, gt)  # the quality the score loosely tracks
        score = float(np.clip(0.30 + 0.55 * q + persona.score_bias + rng.normal(0.0, 0.12), 0.02, 0.99))
        return mask, score, draw

    @staticmethod
    def _apply(mode: str, gt, parts, image, rng: np.random.Generator, r: int, scene: SceneDraw) -> np.ndarray:
        """Apply failure mode ``mode`` to the ground truth ``gt``; ValueError for an unknown mode."""
        if mode == "clean":
            return gt.copy()
        if mode == "dilate":
            return dilate(gt, r)
        if mode == "erode":
            out = erode(gt, r)
            return out if out.any() else gt.copy()
        if mode == "drop_thin":
            return drop_thin(gt, parts, max(1, round(max(gt.shape) / 128.0)), drop_dish=bool(rng.random() < 0.5))
        if mode == "bus_only":
            return bus_only(gt, parts)
        if mode == "false_positive":
            region = bright_region(image, dilate(gt, 1))
            if not region.any() or rng.random() < 0.5:
                region = glare_blob(gt, rng, attached=True)
            return gt | region
        if mode == "wrong_object":
            region = bright_region(image, dilate(gt, 1))
            if region.any() and rng.random() < 0.6:
                return region
            return glare_blob(gt, rng, attached=False) & ~gt
        raise ValueError(f"unknown simulator mode {mode!r}")

    def predict(self, batch: Sequence[TeacherInput], prompts: Sequence[str]) -> tuple[np.ndarray, np.ndarray]:
        """Answer every prompt for every image (eq:teacher-prediction, simulated).

        Parameters
        ----------
        batch : sequence of TeacherInput
            B images, each with its reference mask.
        prompts : sequence of str
            The K prompts.

        Returns
        -------
        tuple of numpy.ndarray
            Masks bool [B,K,H,W] and scores float32 [B,K] (0 = invalid), as :meth:`predict_with_draws`.
        """
        masks, scores, _ = self.predict_with_draws(batch, prompts)
        return masks, scores

    def predict_with_draws(self, batch: Sequence[TeacherInput], prompts: Sequence[str]
                           ) -> tuple[np.ndarray, np.ndarray, list[tuple[SceneDraw, list[PromptDraw]]]]:
        """Answer as :meth:`predict` does, and say what each answer drew (diagnostics: benchmarks/memorisation.py).

        Parameters
        ----------
        batch : sequence of TeacherInput
            B images, each with its reference mask.
        prompts : sequence of str
            The K prompts.

        Returns
        -------
        tuple
            Masks bool [B,K,H,W], scores float32 [B,K] (:func:`pipeline.teachers.base.finalize_answers`) and,
            per image, its :class:`SceneDraw` and one :class:`PromptDraw` per prompt (``prompts`` order).

        Raises
        ------
        InputError
            An image has no reference mask, or one of another size.
        """
        if not batch:
            return np.zeros((0, len(prompts), 0, 0), bool), np.zeros((0, len(prompts)), np.float32), []
        out_masks, out_scores, out_draws = [], [], []
        for item in batch:
            if item.reference is None or "mask" not in item.reference:
                raise InputError(f"simulated teacher: no reference mask for image {item.image_id!r}; "
                                 "the simulator needs the synthetic ground truth (reference.zarr)")
            gt = np.asarray(item.reference["mask"])
            if gt.shape != item.image.shape[:2]:
                raise InputError(f"simulated teacher: reference mask {gt.shape} and image {item.image.shape[:2]} "
                                 f"of {item.image_id!r} differ in size")
            scene = self.scene(item)
            masks, scores, draws = zip(*(self.answer_with_draw(item, p, scene) for p in prompts))
            out_masks.append(np.stack(masks))
            out_scores.append(np.array(scores, np.float32))
            out_draws.append((scene, list(draws)))
        return (*finalize_answers(np.stack(out_masks), np.stack(out_scores)), out_draws)


def persona_for(prompt: str) -> Persona:
    """Return the persona of a prompt of eq:prompt-set.

    Parameters
    ----------
    prompt : str
        A prompt (case and surrounding blanks ignored).

    Returns
    -------
    Persona
        Its persona of :data:`PERSONAS`; any other prompt gets :data:`GENERIC_PERSONA`.
    """
    return PERSONAS.get(prompt.strip().lower(), GENERIC_PERSONA)
