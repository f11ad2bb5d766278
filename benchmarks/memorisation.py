"""Memorisation diagnosis (issue 57 item 1): which of the teacher SIMULATOR's vote errors does the student copy, and
which does it correct, epoch by epoch?

1. Replays the SIMULATOR's draws on the training images (:meth:`SimulatedFoundationTeacher.predict_with_draws`, the
   masks checked byte-equal to ``teacher.zarr``): per image the failure mode each prompt drew and the shared events
   (breakdown, shared_thin, shared_fp).
2. Trains Plain (Stage I on the vote, annotation-free) and the supervised ceiling (the same recipe on the REFERENCE
   masks; NOT annotation-free) and keeps the model after every epoch (:class:`EpochCheckpointer`).
3. Scores each epoch's model on the TRAINING images against the reference masks (the reference masks only score:
   they enter no annotation-free loss), at tau 0.5 and at the epoch's tau calibrated on the validation images by the
   run's rule, beside the vote; the vote's wrong pixels are split by region (:data:`REGIONS`) and by the image's
   draws (:func:`image_groups`): the fraction the student copies (predicts as the wrong vote does) and the fraction
   it corrects.

    python -m benchmarks.memorisation --resolution 64 --set train.recipe=progressive --seed 42

Finished runs (their per-epoch models and scores) are kept in ``--workdir``: a rerun trains and scores only what is
missing, and a killed run resumes from its last epoch.  Figure: ``--figure`` (PNG).  docs/student.md, "Memorisation".
"""

from __future__ import annotations

import datetime
import json
import os
import subprocess
import time
from pathlib import Path
from typing import Any, Mapping, Sequence

import numpy as np

from benchmarks.common import host_record, parser
from benchmarks.study_recipe import build_artifacts
from pipeline import catalog
from pipeline.artifacts.atomic import write_text_if_changed
from pipeline.artifacts.store import open_artifact
from pipeline.evaluation.inference import predict_probs
from pipeline.metrics import image_ious
from pipeline.methods import STAGE_ONE, SUPERVISED_CEILING, get_method
from pipeline.params import PAPER
from pipeline.profiles import load_profile
from pipeline.runtime.errors import InputError
from pipeline.teachers.base import TeacherInput, manifest_extras
from pipeline.teachers.simulated import (MISS, MODES, SIMULATOR_VERSION, SimulatedFoundationTeacher, dilate, erode,
                                         open_mask)
from pipeline.thresholds import EPOCH_TAU_GRID, calibrate_threshold, mask_from_probs
from pipeline.training.checkpointing import FileCheckpointer
from pipeline.training.inputs import load_inputs

REPO = Path(__file__).resolve().parents[1]
#: Plain (Stage I on the vote) and the supervised ceiling (reference masks; NOT annotation-free)
METHODS = (STAGE_ONE, SUPERVISED_CEILING)
#: pixel regions, a partition of every image (:func:`region_labels`)
REGIONS = ("thin", "boundary", "interior", "fp_blob", "background")
#: per image and region: the vote's wrong pixels, those the student predicts as the vote does (copies), the vote's
#: right pixels, those the student gets wrong (its own errors)
COUNTS = ("vote_wrong", "copied", "vote_right", "own_wrong")
#: the boundary band's half-width in px at 64 px (scaled with the side)
BAND_PX_AT_64 = 2
#: the fixed threshold beside the calibrated one
FIXED_TAU = PAPER.calibrate.fixed_tau
BOOTSTRAP_RESAMPLES = 2000
#: the simulator's scale difficulty (:func:`pipeline.teachers.simulated.scale_difficulty`) from which a target
#: counts as small: about 2 % of the frame and less
SMALL_SCALE = 0.5
#: a group of images needs this many members to be reported
MIN_GROUP = 5


# ----------------------------------------------------------------------------------------------- the draws


def training_rows(manifest) -> np.ndarray:
    """Indices of the manifest's ``split == "train"`` rows (the order :mod:`pipeline.training.inputs` uses)."""
    return np.flatnonzero((manifest.df["split"] == "train").to_numpy())


def replay_draws(artifacts: Path, rows: np.ndarray) -> tuple[list[dict], np.ndarray]:
    """(one record per row of ``rows``: the scene's draws and each prompt's, the replayed masks bool [N,K,H,W]) of
    the SIMULATOR that wrote ``artifacts``' ``teacher.zarr`` (its seed and prompts from the artifact's attrs).

    Raises
    ------
    InputError
        ``teacher.zarr`` is not the SIMULATOR's, or the replay's masks or scores differ from it (another simulator
        version or code): the draws would not describe the vote.
    """
    teacher = open_artifact(catalog.path("teacher", artifacts), "teacher")
    fp = teacher.attrs.get("teacher") or {}
    if not fp.get("simulator") or fp.get("simulator_version") != SIMULATOR_VERSION:
        raise InputError(f"{teacher.path}: not written by the teacher SIMULATOR version {SIMULATOR_VERSION} "
                         f"(attrs teacher={fp}); the diagnosis replays the simulator's draws")
    prompts = list(teacher.attrs["prompts"])
    man = open_artifact(catalog.path("manifest", artifacts), "manifest").df.reset_index(drop=True)
    images = open_artifact(catalog.path("images", artifacts), "images")["image"]
    ref = open_artifact(catalog.path("reference", artifacts), "reference")
    parts = ref["parts"] if "parts" in ref else None
    extras = manifest_extras(man)
    items = [TeacherInput(str(man.at[i, "image_id"]), str(man.at[i, "sha256"]), np.asarray(images[i]), "identity",
                          {"mask": np.asarray(ref["mask"][i], bool),
                           **({"parts": np.asarray(parts[i])} if parts is not None else {})}, extras[i])
             for i in rows]
    sim = SimulatedFoundationTeacher(seed=int(fp["seed"]), resolution=items[0].image.shape[:2] if items else None)
    masks, scores, draws = sim.predict_with_draws(items, prompts)
    stored_masks = np.stack([np.asarray(teacher["masks"][i], bool) for i in rows])
    stored_scores = np.stack([np.asarray(teacher["scores"][i], np.float32) for i in rows])
    if not (np.array_equal(masks, stored_masks) and np.array_equal(scores, stored_scores)):
        raise InputError(f"{teacher.path}: the replayed SIMULATOR answers differ from the stored ones; rebuild the "
                         "artifacts with this code")
    records = []
    for item, (scene, per_prompt), s in zip(items, draws, scores):
        records.append({"image_id": item.image_id, "difficulty": round(scene.difficulty, 4),
                        "scale": round(scene.scale, 4), "breakdown": scene.breakdown,
                        "shared_thin": scene.shared_thin, "shared_fp": scene.shared_fp,
                        "modes": [d.mode for d in per_prompt], "valid": [bool(v > 0) for v in s],
                        "thin_takers": sum(d.shared_thin for d in per_prompt),
                        "fp_takers": sum(d.shared_fp for d in per_prompt)})
    return records, masks


def image_groups(records: Sequence[Mapping[str, Any]]) -> dict[str, np.ndarray]:
    """Name -> bool [N]: every image; by the shared events (``breakdown``; ``shared_thin`` / ``shared_fp``: at least
    two prompts took part, enough to carry a six-prompt vote's minority; ``no shared event``); and, per failure
    mode, the images where at least two valid answers drew it (``2+ prompts: <mode>``); by the simulator's scale
    difficulty (small targets: >= :data:`SMALL_SCALE`, 1 at 0.4 % of the frame and below).  Groups overlap."""
    n = len(records)
    out = {"all": np.ones(n, bool)}
    out["breakdown"] = np.array([r["breakdown"] for r in records], bool)
    out["shared_thin"] = np.array([r["thin_takers"] >= 2 for r in records], bool)
    out["shared_fp"] = np.array([r["fp_takers"] >= 2 for r in records], bool)
    out["no shared event"] = ~(out["breakdown"] | out["shared_thin"] | out["shared_fp"])
    small = np.array([r["scale"] >= SMALL_SCALE for r in records], bool)
    out["small target"], out["large target"] = small, ~small
    for m in MODES:
        out[f"2+ prompts: {m}"] = np.array([sum(md == m and v for md, v in zip(r["modes"], r["valid"])) >= 2
                                            for r in records], bool)
    return out


def draw_summary(records: Sequence[Mapping[str, Any]], prompts: Sequence[str]) -> dict:
    """Rates of the shared events and, per prompt, the share of images on which it drew each mode (or missed)."""
    n = max(len(records), 1)
    per_prompt = {}
    for k, p in enumerate(prompts):
        modes = [r["modes"][k] for r in records]
        per_prompt[p] = {m: round(modes.count(m) / n, 4) for m in (MISS, *MODES)}
    return {"n_images": len(records),
            **{e: round(sum(bool(r[e]) for r in records) / n, 4) for e in ("breakdown", "shared_thin", "shared_fp")},
            "modes_per_prompt": per_prompt}


# ----------------------------------------------------------------------------------------------- the regions


def band_px(side: int) -> int:
    """The boundary band's half-width at a side of ``side`` px: :data:`BAND_PX_AT_64` scaled, at least 1."""
    return max(1, int(round(BAND_PX_AT_64 * side / 64)))


def thin_radius(side: int) -> int:
    """The opening radius that finds thin parts: the SIMULATOR's thin-structure radius (1 px per 128 px, at least
    1), so that "thin" means what the simulator's drop_thin removes without part labels."""
    return max(1, int(round(side / 128.0)))


def region_labels(gt: np.ndarray, vote: np.ndarray, band: int, radius: int) -> np.ndarray:
    """uint8 [N,H,W] index into :data:`REGIONS` of every pixel, a partition by priority:

    ``thin``: reference pixels an opening of ``radius`` px removes; ``boundary``: other pixels within ``band`` px of
    the reference boundary (either side); ``interior``: the other reference pixels; ``fp_blob``: vote-positive
    pixels outside the reference and its band; ``background``: the rest.  An empty reference has no thin, boundary
    or interior pixel.
    """
    out = np.empty(gt.shape, np.uint8)
    for i, (g, v) in enumerate(zip(np.asarray(gt, bool), np.asarray(vote, bool))):
        thin = g & ~open_mask(g, radius)
        near = (dilate(g, band) & ~g) | (g & ~erode(g, band)) if g.any() else np.zeros_like(g)
        lab = np.full(g.shape, REGIONS.index("background"), np.uint8)
        lab[~g & ~near & v] = REGIONS.index("fp_blob")
        lab[g & ~near] = REGIONS.index("interior")
        lab[near] = REGIONS.index("boundary")
        lab[thin] = REGIONS.index("thin")
        out[i] = lab
    return out


def error_counts(pred: np.ndarray, gt: np.ndarray, vote: np.ndarray, labels: np.ndarray) -> np.ndarray:
    """int64 [N,R,4] per image and region (:data:`REGIONS`): the :data:`COUNTS` of ``pred`` against ``gt`` and
    ``vote`` (bool [N,H,W] each)."""
    pred, gt, vote = (np.asarray(a, bool) for a in (pred, gt, vote))
    wrong = vote != gt
    n = len(gt)
    flat = labels.reshape(n, -1).astype(np.int64)
    cols = (wrong, wrong & (pred == vote), ~wrong, ~wrong & (pred != gt))
    out = np.empty((n, len(REGIONS), len(COUNTS)), np.int64)
    r = len(REGIONS)
    for c, m in enumerate(cols):
        m = m.reshape(n, -1)
        for i in range(n):
            out[i, :, c] = np.bincount(flat[i][m[i]], minlength=r)
    return out


def copy_rates(counts: np.ndarray) -> dict[str, dict[str, float]]:
    """Per region, pooled over the images of ``counts`` [N,R,4]: ``copied`` = copied / vote_wrong (the share of the
    vote's errors the student repeats; 1 - it: corrected), ``own`` = own_wrong / vote_right, and the pixel counts
    (NaN rates where there is nothing to count)."""
    tot = counts.sum(axis=0).astype(np.float64)
    out = {}
    for k, name in enumerate(REGIONS):
        vw, cp, vr, ow = tot[k]
        out[name] = {"copied": cp / vw if vw else float("nan"), "own": ow / vr if vr else float("nan"),
                     "vote_wrong_px": int(vw), "vote_right_px": int(vr)}
    return out


def bootstrap_ratio(num: np.ndarray, den: np.ndarray, rng: np.random.Generator,
                    resamples: int = BOOTSTRAP_RESAMPLES) -> tuple[float, float, float]:
    """(sum num / sum den, 95 % percentile interval) over images resampled with replacement; NaNs where den is 0."""
    num, den = np.asarray(num, np.float64), np.asarray(den, np.float64)
    if den.sum() == 0:
        return float("nan"), float("nan"), float("nan")
    idx = rng.integers(0, len(num), size=(resamples, len(num)))
    d = den[idx].sum(1)
    r = np.where(d > 0, num[idx].sum(1) / np.maximum(d, 1e-12), np.nan)
    lo, hi = np.nanpercentile(r, [2.5, 97.5])
    return float(num.sum() / den.sum()), float(lo), float(hi)


def bootstrap_mean(x: np.ndarray, rng: np.random.Generator, resamples: int = BOOTSTRAP_RESAMPLES
                   ) -> tuple[float, float, float]:
    """(mean, 95 % percentile interval) of per-image values ``x`` over images resampled with replacement."""
    x = np.asarray(x, np.float64)
    m = x[rng.integers(0, len(x), size=(resamples, len(x)))].mean(1)
    lo, hi = np.percentile(m, [2.5, 97.5])
    return float(x.mean()), float(lo), float(hi)


# ----------------------------------------------------------------------------------------------- training


class EpochCheckpointer:
    """The loop's resume state in ``<directory>/state.pt`` (:class:`~pipeline.training.checkpointing.FileCheckpointer`)
    and every saved state's ``model`` in ``<directory>/epochs/e<epoch>.pt``: a killed run resumes, and each epoch's
    weights stay for scoring."""

    def __init__(self, directory: str | Path):
        self.directory = Path(directory)
        self.resume = FileCheckpointer(self.directory)

    def __repr__(self) -> str:
        return str(self.directory)

    def load(self, run_key: Mapping[str, Any]) -> dict | None:
        return self.resume.load(run_key)

    def save(self, state: dict) -> None:
        save_weights(state["model"], self.epoch_path(int(state["epoch"])))
        self.resume.save(state)

    def epoch_path(self, epoch: int) -> Path:
        return self.directory / "epochs" / f"e{epoch:04d}.pt"

    def epochs(self) -> list[int]:
        """The epochs whose weights are kept, ascending."""
        return sorted(int(p.stem[1:]) for p in (self.directory / "epochs").glob("e*.pt"))


def save_weights(state_dict: Mapping[str, Any], path: Path) -> None:
    """A model's state dict at ``path`` (tensors only: :func:`load_weights` reads it with ``weights_only``),
    replaced atomically."""
    import torch

    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    torch.save({k: v.detach().cpu() for k, v in state_dict.items()}, tmp)
    os.replace(tmp, path)


def load_weights(path: Path) -> dict:
    import torch

    return torch.load(path, map_location="cpu", weights_only=True)


def git_commit() -> str:
    """The checkout's commit (``+dirty`` when tracked files differ from it), or ``unknown``."""
    try:
        sha = subprocess.run(["git", "rev-parse", "HEAD"], cwd=REPO, capture_output=True, text=True,
                             check=True).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"], cwd=REPO,
                               capture_output=True, text=True, check=True).stdout.strip()
        return sha + ("+dirty" if dirty else "")
    except (OSError, subprocess.CalledProcessError):
        return "unknown"


def train_run(method: str, cfg: Mapping[str, Any], data, val, seed: int, run_dir: Path, commit: str) -> dict:
    """Train (``method``, ``seed``) with every epoch's weights kept in ``run_dir`` (resumed there); its
    ``done.json`` (log, selected epoch, ``commit``: the code it trained at) is written last and makes a rerun skip
    it."""
    from pipeline.training import loop as training

    done = run_dir / "done.json"
    if done.exists():
        return json.loads(done.read_text())
    t0 = time.perf_counter()
    ckpt = EpochCheckpointer(run_dir)
    res = training.train(get_method(method), cfg, data, val, seed, checkpointer=ckpt, device="cpu",
                         show_progress=False)
    save_weights(res.model.state_dict(), run_dir / "final.pt")
    log = res.log
    out = {"method": method, "seed": seed, "commit": commit, "selected_epoch": int(res.selected_epoch),
           "epochs_run": int(log["epoch"].max()), "low_res_epochs": res.info.get("low_res_epochs"),
           "stopped": res.info.get("stopped"), "steps_run": res.info.get("steps_run"),
           "val_iou_cal": [None if not np.isfinite(v) else float(v) for v in log["val_iou_cal"]],
           "seconds": time.perf_counter() - t0}
    write_text_if_changed(done, json.dumps(out, indent=1))
    return out


# ----------------------------------------------------------------------------------------------- scoring


def predict(model, state: Mapping[str, Any], images: np.ndarray) -> np.ndarray:
    model.load_state_dict(state)
    return predict_probs(model, images, device="cpu", precision="fp32")


def score_epoch(probs: np.ndarray, val_probs: np.ndarray, val_masks: np.ndarray, gt: np.ndarray, vote: np.ndarray,
                labels: np.ndarray, tau_rule: str) -> dict:
    """One model's training-image scores: per threshold (``05``: :data:`FIXED_TAU`; ``cal``: calibrated on the
    validation images by ``tau_rule``) the per-image IoU against the reference and against the vote, and the
    :func:`error_counts`."""
    tau, _ = calibrate_threshold(val_probs, val_masks, EPOCH_TAU_GRID, tau_rule)
    out: dict[str, Any] = {"tau_cal": float(tau)}
    for key, t in (("05", FIXED_TAU), ("cal", tau)):
        pred = mask_from_probs(probs, t)
        out[key] = {"iou_ref": image_ious(pred, gt), "iou_vote": image_ious(pred, vote),
                    "counts": error_counts(pred, gt, vote, labels)}
    return out


def scored_epochs(epochs: Sequence[int], stride: int, low_res_epochs: int | None) -> list[int]:
    """The kept epochs scored: every ``stride``-th, the last half-side one and the last one (scoring every epoch
    costs a prediction over the training images each)."""
    last = max(epochs) if epochs else 0
    keep = {e for e in epochs if e % max(int(stride), 1) == 0 or e == last or e == (low_res_epochs or -1)}
    return sorted(keep)


def score_run(method: str, cfg: Mapping[str, Any], seed: int, run_dir: Path, epochs: Sequence[int],
              images: np.ndarray, gt: np.ndarray, vote: np.ndarray, labels: np.ndarray, val, tau_rule: str) -> dict:
    """The scores (:func:`score_epoch`) of ``epochs``' weights and, last (epoch -1), the run's returned (selected,
    averaged) model, stacked; each model's cached in ``run_dir/scores/`` (numbers only, ``allow_pickle`` off) so
    that a killed scoring resumes.  A cache of other training images (another count) is recomputed."""
    from pipeline.training import loop as training

    model = None
    rows = []
    for e in [*epochs, -1]:
        cache = run_dir / "scores" / f"{'final' if e == -1 else f'e{e:04d}'}.npz"
        row = None
        if cache.exists():
            with np.load(cache, allow_pickle=False) as z:
                row = {k: z[k] for k in z.files}
            if row["iou_ref_05"].shape != (len(gt),):
                row = None
        if row is None:
            if model is None:
                model = training.build_model(get_method(method), cfg, seed)
            state = load_weights(run_dir / "final.pt" if e == -1 else EpochCheckpointer(run_dir).epoch_path(e))
            r = score_epoch(predict(model, state, images), predict(model, state, val.images), val.masks, gt, vote,
                            labels, tau_rule)
            row = {"tau_cal": np.float64(r["tau_cal"]),
                   **{f"{f}_{key}": r[key][f] for key in ("05", "cal") for f in ("iou_ref", "iou_vote", "counts")}}
            cache.parent.mkdir(parents=True, exist_ok=True)
            tmp = cache.with_name(f".{cache.stem}.tmp-{os.getpid()}.npz")
            np.savez_compressed(tmp, **row)
            os.replace(tmp, cache)
        rows.append(row)
    out = {"epochs": np.asarray(list(epochs), np.int64)}
    for k in rows[0]:
        out[k] = np.stack([np.asarray(r[k]) for r in rows])
    return out


# ----------------------------------------------------------------------------------------------- the summary


def _r(x: float, nd: int = 4):
    return None if x is None or not np.isfinite(x) else round(float(x), nd)


def finite(obj: Any) -> Any:
    """``obj`` with every float rounded to 4 places and NaN/inf as None (strict JSON), tuples as lists."""
    if isinstance(obj, Mapping):
        return {k: finite(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [finite(v) for v in obj]
    if isinstance(obj, (float, np.floating)):
        return _r(obj)
    if isinstance(obj, np.integer):
        return int(obj)
    if isinstance(obj, np.bool_):
        return bool(obj)
    return obj


def curves(scores: Mapping[str, np.ndarray], groups: Mapping[str, np.ndarray]) -> dict:
    """Per threshold, per epoch (the final model last): mean IoU against the reference and the vote, per region the
    copied share of the vote's errors and the own-error share of its right pixels, per group the mean IoU."""
    out = {"epochs": [int(e) for e in scores["epochs"]], "tau_cal": [_r(t, 3) for t in scores["tau_cal"]]}
    for key in ("05", "cal"):
        ref, agree, counts = scores[f"iou_ref_{key}"], scores[f"iou_vote_{key}"], scores[f"counts_{key}"]
        rates = [copy_rates(c) for c in counts]
        out[key] = {"iou_ref": [_r(x) for x in ref.mean(1)], "iou_vote": [_r(x) for x in agree.mean(1)],
                    "copied": {g: [_r(r[g]["copied"]) for r in rates] for g in REGIONS},
                    "own": {g: [_r(r[g]["own"]) for r in rates] for g in REGIONS},
                    "groups": {name: {"iou_ref": [_r(x) for x in ref[:, sel].mean(1)],
                                      "copied": [_r(copy_rate_all(c[sel])) for c in counts]}
                               for name, sel in groups.items() if sel.sum() >= MIN_GROUP}}
    return out


def copy_rate_all(counts: np.ndarray) -> float:
    """Copied share of the vote's wrong pixels over every region of ``counts`` [N,R,4]."""
    t = counts.sum(axis=(0, 1))
    return t[1] / t[0] if t[0] else float("nan")


def summarize(scores: Mapping[str, np.ndarray], vote_iou: np.ndarray, groups: Mapping[str, np.ndarray],
              rng: np.random.Generator) -> dict:
    """The run's answer in numbers (each with a per-image bootstrap 95 % interval; one seed, so no seed noise):
    at the final model and at the epoch of the highest training-image IoU (chosen on these images: it flatters the
    peak), the IoU against the reference minus the vote's, the peak minus the final, and the copied share per
    region and per group."""
    out = {}
    for key in ("05", "cal"):
        ref, counts = scores[f"iou_ref_{key}"], scores[f"counts_{key}"]
        means = ref[:-1].mean(1)
        peak = int(np.argmax(means))
        at = {"final": len(ref) - 1, "peak": peak}
        s: dict[str, Any] = {"peak_epoch": int(scores["epochs"][peak]),
                             "final_tau_cal": _r(scores["tau_cal"][-1], 3)}
        for name, i in at.items():
            s[name] = {"iou_ref": bootstrap_mean(ref[i], rng), "minus_vote": bootstrap_mean(ref[i] - vote_iou, rng),
                       "agreement_with_vote": _r(scores[f"iou_vote_{key}"][i].mean()),
                       "copied": {g: bootstrap_ratio(counts[i][:, k, 1], counts[i][:, k, 0], rng)
                                  for k, g in enumerate(REGIONS)},
                       "own": {g: bootstrap_ratio(counts[i][:, k, 3], counts[i][:, k, 2], rng)
                               for k, g in enumerate(REGIONS)},
                       "pixels": {g: {"copied": int(counts[i][:, k, 1].sum()), "own": int(counts[i][:, k, 3].sum())}
                                  for k, g in enumerate(REGIONS)},
                       "groups": {name_g: {"n": int(sel.sum()),
                                           "iou_ref": _r(ref[i][sel].mean()), "vote_iou": _r(vote_iou[sel].mean()),
                                           "minus_vote": bootstrap_mean(ref[i][sel] - vote_iou[sel], rng),
                                           "copied": bootstrap_ratio(counts[i][sel][:, :, 1].sum(1),
                                                                     counts[i][sel][:, :, 0].sum(1), rng)}
                                  for name_g, sel in groups.items() if sel.sum() >= MIN_GROUP}}
        s["peak_minus_final"] = bootstrap_mean(ref[peak] - ref[-1], rng)
        out[key] = s
    return finite(out)


def figure(doc: Mapping[str, Any]):
    """Four panels: training-image IoU against the reference per epoch (Plain, the ceiling, the vote), the copied
    share of the vote's errors per region for Plain and for the ceiling, and Plain's IoU minus the vote's per group
    at the final model."""
    from matplotlib.figure import Figure

    from pipeline.report.figures import CHART_FONT, method_style
    import matplotlib

    with matplotlib.rc_context(CHART_FONT):
        fig = Figure(figsize=(12, 8.4))
        axes = fig.subplots(2, 2)
        ax = axes[0, 0]
        for m, run in doc["runs"].items():
            c = run["curves"]
            ep = c["epochs"]
            st = method_style(m)
            for key, ls in (("cal", "-"), ("05", ":")):
                ax.plot(ep, c[key]["iou_ref"][:-1], ls, color=st["color"], lw=1.2,
                        label=f"{m} (tau {'cal' if key == 'cal' else FIXED_TAU})")
            ax.plot(ep, c["cal"]["iou_vote"][:-1], "--", color=st["color"], lw=0.8, alpha=0.6,
                    label=f"{m}: IoU with the vote (tau cal)")
            if run.get("low_res_epochs"):
                ax.axvline(run["low_res_epochs"] + 0.5, color="#999", lw=0.6)
        ax.axhline(doc["vote"]["iou_ref"], color="#e08000", lw=1.2, label="the vote (Plain's labels)")
        ax.set(title="Training images: IoU against the reference", xlabel="epoch (grey line: end of half-side epochs)",
               ylabel="Image IoU", ylim=(0, 1))
        ax.legend(fontsize=7, loc="lower right")
        for ax, m in ((axes[0, 1], STAGE_ONE), (axes[1, 0], SUPERVISED_CEILING)):
            run = doc["runs"].get(m)
            if run is None:
                ax.set_visible(False)
                continue
            c = run["curves"]
            for j, g in enumerate(REGIONS):
                color = f"C{j}" if g != "background" else "#777"
                if g != "background":
                    ax.plot(c["epochs"], c["cal"]["copied"][g][:-1], lw=1.2, color=color,
                            label=f"{g}: copied ({doc['vote']['regions'][g]['vote_wrong_px']:,} px wrong in the vote)")
                if g != "fp_blob":
                    ax.plot(c["epochs"], c["cal"]["own"][g][:-1], "--", lw=0.9, color=color,
                            label=f"{g}: own errors ({doc['vote']['regions'][g]['vote_right_px']:,} px right)")
            ax.set(title=f"{m}: vote errors copied (solid), own errors (dashed)", xlabel="epoch",
                   ylabel="share of the region's pixels (tau cal)", ylim=(0, 1.3), yticks=np.linspace(0, 1, 6))
            ax.legend(fontsize=6.5, ncol=2)
        ax = axes[1, 1]
        for j, (m, run) in enumerate(doc["runs"].items()):
            groups = run["summary"]["cal"]["final"]["groups"]
            names = list(groups)
            y = np.arange(len(names)) + (j - 0.5) * 0.35
            mid = [groups[n]["minus_vote"][0] for n in names]
            err = np.array([[mid[i] - groups[n]["minus_vote"][1], groups[n]["minus_vote"][2] - mid[i]]
                            for i, n in enumerate(names)]).T
            ax.barh(y, mid, height=0.35, xerr=err, color=method_style(m)["color"], label=m, alpha=0.8)
            if j == 0:
                ax.set_yticks(np.arange(len(names)), [f"{n} ({groups[n]['n']})" for n in names], fontsize=7)
        ax.axvline(0, color="k", lw=0.8)
        ax.set(title="Final model: IoU minus the vote's, per image group (95 % bootstrap)",
               xlabel="training-image IoU - vote IoU (tau cal)")
        ax.legend(fontsize=7)
        fig.suptitle("Memorisation diagnosis (teacher SIMULATOR, synthetic benchmark; one seed)", fontsize=11)
        fig.tight_layout()
    return fig


def main(argv=None) -> dict:
    ap = parser(__doc__, artifacts=None, workdir=".cache/memorisation", profile="reduced", resolution=64,
                device="cpu", threads=1, out="reports/memorisation/memorisation-64.json", set=[])
    ap.add_argument("--seed", type=int, default=42)
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=list(METHODS))
    ap.add_argument("--figure", default=None, help="PNG of the curves (default: none)")
    ap.add_argument("--train-only", action="store_true", help="train (and keep) the runs, score nothing")
    ap.add_argument("--score-stride", type=int, default=4,
                    help="score every n-th epoch (and the last half-side and the last one); 1: every epoch")
    args = ap.parse_args(argv)
    sets = [f"data.resolution={args.resolution}", *args.sets]
    params = load_profile(args.profile, sets)
    workdir = Path(args.workdir).resolve()
    artifacts = Path(args.artifacts) if args.artifacts else build_artifacts(workdir, args.profile, sets, args.device)
    cfg = {**params["train"], "num_threads": args.threads}

    commit = git_commit()  # the code this invocation runs (imported now; later edits do not reach it)
    data = {}
    for m in args.methods:
        data[m], val, _ = load_inputs(artifacts, get_method(m), cfg)
    runs_dir = workdir / "runs" / f"{args.profile}-{args.resolution}-{params['train']['recipe']}"
    if args.train_only:
        return {"trained": {m: train_run(m, cfg, data[m], val, args.seed, runs_dir / f"{m}-s{args.seed}", commit)
                            for m in args.methods}}

    man = open_artifact(catalog.path("manifest", artifacts), "manifest")
    rows = training_rows(man)
    ids = man.df["image_id"].astype(str).to_numpy()[rows]
    for m in args.methods:
        if list(data[m].image_ids) != list(ids):
            raise InputError(f"{m}: its training rows differ from the manifest's train split; the diagnosis scores "
                             "every training image with a reference mask")
    records, _ = replay_draws(artifacts, rows)
    groups = image_groups(records)
    images = np.asarray(data[args.methods[0]].images[:])
    ref = open_artifact(catalog.path("reference", artifacts), "reference")
    gt = np.stack([np.asarray(ref["mask"][i], bool) for i in rows])
    cons = open_artifact(catalog.path("consensus", artifacts), "consensus")
    vote = np.stack([np.asarray(cons["voted"][i], bool) for i in rows])
    side = int(gt.shape[-1])
    labels = region_labels(gt, vote, band_px(side), thin_radius(side))
    vote_iou = image_ious(vote, gt)
    vote_counts = error_counts(vote, gt, vote, labels)
    tau_rule = str(params["calibrate"]["tau_rule"])
    rng = np.random.default_rng(args.seed)
    teacher_attrs = open_artifact(catalog.path("teacher", artifacts), "teacher").attrs
    doc: dict[str, Any] = {
        "info": {"what": "memorisation diagnosis (issue 57 item 1): students scored on their TRAINING images against "
                         "the reference masks; teacher SIMULATOR (synthetic benchmark)",
                 "commit": commit, "date": datetime.date.today().isoformat(), "host": host_record(),
                 "threads": args.threads,
                 "profile": args.profile, "resolution": args.resolution, "sets": sets,
                 "recipe": params["train"]["recipe"], "seed": args.seed, "n_train": len(rows), "n_val": len(val),
                 "simulator_version": SIMULATOR_VERSION, "teacher_seed": teacher_attrs["teacher"]["seed"],
                 "prompts": list(teacher_attrs["prompts"]), "replay_matches_teacher_zarr": True,
                 "band_px": band_px(side), "thin_opening_radius_px": thin_radius(side), "fixed_tau": FIXED_TAU,
                 "tau_rule": tau_rule, "score_stride": args.score_stride, "bootstrap": f"{BOOTSTRAP_RESAMPLES} resamples of the training images, "
                                                    "95 % percentile intervals; one seed: no seed noise included",
                 "ceiling": "supervised_ceiling trains on the REFERENCE masks: NOT annotation-free"},
        "draws": {"summary": draw_summary(records, teacher_attrs["prompts"]),
                  "groups": {k: int(v.sum()) for k, v in groups.items()},
                  "per_image": [{**r, "vote_iou": _r(v)} for r, v in zip(records, vote_iou)]},
        "vote": {"iou_ref": _r(vote_iou.mean()), "iou_ref_ci": bootstrap_mean(vote_iou, rng),
                 "regions": copy_rates(vote_counts),
                 "groups": {k: {"n": int(v.sum()), "iou_ref": _r(vote_iou[v].mean())} for k, v in groups.items()
                            if v.sum() >= MIN_GROUP}},
        "runs": {}}
    for m in args.methods:  # each run is written as it finishes: the first answer comes before the second run
        run_dir = runs_dir / f"{m}-s{args.seed}"
        trained = train_run(m, cfg, data[m], val, args.seed, run_dir, commit)
        epochs = scored_epochs(EpochCheckpointer(run_dir).epochs(), args.score_stride, trained.get("low_res_epochs"))
        scores = score_run(m, cfg, args.seed, run_dir, epochs, images, gt, vote, labels, val, tau_rule)
        doc["runs"][m] = {**{k: v for k, v in trained.items() if k != "val_iou_cal"},
                          "annotation_free": get_method(m).annotation_free,
                          "curves": curves(scores, groups), "summary": summarize(scores, vote_iou, groups, rng)}
        print(f"{m}: final IoU {doc['runs'][m]['summary']['cal']['final']['iou_ref'][0]:.3f} (vote "
              f"{doc['vote']['iou_ref']:.3f}), peak epoch {doc['runs'][m]['summary']['cal']['peak_epoch']}", flush=True)
        print(answer_table(doc), flush=True)
        last = m == args.methods[-1]  # the figure once, at the end (the JSON after each run: an early answer)
        write_outputs(doc, Path(args.out), Path(args.figure) if args.figure and last else None)
    return doc


def _ci(v) -> str:
    return f"{v[0]:.3f} [{v[1]:.3f}, {v[2]:.3f}]" if v and v[0] is not None else "n/a"


def answer_table(doc: Mapping[str, Any], key: str = "cal") -> str:
    """Markdown tables of each run's answer at threshold ``key``: IoU on the training images (peak, final, the
    vote), the copied share of the vote's wrong pixels per region and, per image group, the final IoU minus the
    vote's (95 % bootstrap intervals over the training images)."""
    runs = doc["runs"]
    lines = ["| run | peak epoch | IoU at the peak | final IoU | final - vote | peak - final | IoU with the vote (final) |",
             "|---|---|---|---|---|---|---|"]
    for m, r in runs.items():
        s = r["summary"][key]
        lines.append(f"| {m} | {s['peak_epoch']} | {_ci(s['peak']['iou_ref'])} | {_ci(s['final']['iou_ref'])} | "
                     f"{_ci(s['final']['minus_vote'])} | {_ci(s['peak_minus_final'])} | "
                     f"{s['final']['agreement_with_vote']:.3f} |")
    lines += ["", "| region (vote's wrong px) | " + " | ".join(f"{m}: copied at the peak | {m}: copied, final"
                                                          for m in runs) + " |",
              "|---|" + "---|---|" * len(runs)]
    for g in REGIONS:
        cells = [f"{_ci(r['summary'][key]['peak']['copied'][g])} | {_ci(r['summary'][key]['final']['copied'][g])}"
                 for r in runs.values()]
        lines.append(f"| {g} ({doc['vote']['regions'][g]['vote_wrong_px']:,}) | " + " | ".join(cells) + " |")
    groups = next(iter(runs.values()))["summary"][key]["final"]["groups"]
    lines += ["", "| images (n) | vote IoU | " + " | ".join(f"{m}: final - vote | {m}: copied" for m in runs) + " |",
              "|---|---|" + "---|---|" * len(runs)]
    for g, v in groups.items():
        cells = [f"{_ci(r['summary'][key]['final']['groups'][g]['minus_vote'])} | "
                 f"{_ci(r['summary'][key]['final']['groups'][g]['copied'])}" for r in runs.values()]
        lines.append(f"| {g} ({v['n']}) | {v['vote_iou']:.3f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def write_outputs(doc: Mapping[str, Any], out: Path, figure_path: Path | None) -> None:
    """The JSON at ``out`` and, with ``figure_path``, the PNG of :func:`figure`, each replaced atomically."""
    from pipeline.report.figures import png_bytes

    out.parent.mkdir(parents=True, exist_ok=True)
    write_text_if_changed(out, json.dumps(finite(doc), indent=1, allow_nan=False))
    print(f"wrote {out}", flush=True)
    if figure_path is not None:
        figure_path.parent.mkdir(parents=True, exist_ok=True)
        tmp = figure_path.with_name(f".{figure_path.name}.tmp-{os.getpid()}")
        tmp.write_bytes(png_bytes(figure(doc)))
        os.replace(tmp, figure_path)
        print(f"wrote {figure_path}", flush=True)


if __name__ == "__main__":
    main()
