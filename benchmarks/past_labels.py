"""Past the labels (issue 57): screen Stage-I levers that may learn past the voted masks, beside Plain and the
supervised ceiling, on the synthetic benchmark (its teacher is a SIMULATOR).

Each variant is Plain (Stage I) under the base recipe with one lever (:data:`VARIANTS`); ``self_training`` is a
round of Noisy Student from the ``plain`` run of the same seed (:mod:`pipeline.training.self_training`).  The
reference masks pick tau (on the validation images) and score the test images, once; they never enter an
annotation-free variant's loss.  ``ceiling`` trains on them: NOT annotation-free, a reference point only.

Cost is counted in training images seen (optimizer steps x batch) plus relabelling forward passes at
:data:`RELABEL_WEIGHT` of a training image each (a forward pass is about a third of a forward and backward).

``--fit-of-saved`` scores saved runs: their fit on the training images, the test images at the calibrated tau,
and, screened beside it, a threshold per image (:func:`pipeline.thresholds.calibrate_relative_threshold`, on the
same validation masks; :func:`relative_tau_gain`), a departure that no verdict scores.

    python -m benchmarks.past_labels --profile reduced --resolution 64 --set train.recipe=progressive \
        --seeds 42 --variants plain ceiling self_training bootstrap ignore_band --out past_labels.json
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from benchmarks.common import host_record, parser, resumed_runs, run_jobs
from benchmarks.memorisation import COUNTS, REGIONS, band_px, error_counts, region_labels, thin_radius
from benchmarks.study_recipe import (add_data_size_options, build_artifacts, data_size_sets, load_study_data,
                                     scored_test_rows)
from pipeline import catalog
from pipeline.catalog import RESUME_STATE_FILE
from pipeline.artifacts.atomic import atomic_path
from pipeline.artifacts.store import open_artifact
from pipeline.evaluation.inference import predict_probs
from pipeline.methods import CONTINUATION, PROPOSED, STAGE_ONE, SUPERVISED_CEILING, get_method
from pipeline.metrics import image_ious
from pipeline.profiles import load_profile
from pipeline.report.dvc_results import distillation_efficiency
from pipeline.runtime.device import resolve_device
from pipeline.stats import claim_status, paired_seed_image_t
from pipeline.thresholds import (EPOCH_TAU_GRID, calibrate_relative_threshold, calibrate_threshold,
                                 mask_from_probs, masks_from_relative)
from pipeline.training.inputs import read_rows
from pipeline.training import loop as training
from pipeline.training.loop import build_model
from pipeline.training.self_training import flip_tta_probs, fused_targets
from pipeline.training.checkpointing import FileCheckpointer, NoCheckpointer

#: a relabelling forward pass, in training images (forward + backward ~ 3 forward passes)
RELABEL_WEIGHT = 1.0 / 3.0
#: flip test-time augmentation: two forward passes per image
TTA_PASSES = 2

#: the ``photometric`` variants' changes of ``train.augmentation`` (merged into the base's section: :func:`overlay`)
PHOTOMETRIC = {"flare_probability": 0.3, "exposure_range": [0.25, 2.0]}
#: variant -> (``train.*`` changes of the base recipe, which training data, what it is).  One lever each.
VARIANTS: dict[str, tuple[dict, str, str]] = {
    "plain": ({}, "voted", "Plain Student: the base recipe on the voted masks"),
    "ceiling": ({}, "reference", "supervised ceiling: the reference masks, NOT annotation-free"),
    "self_training": ({}, "self_training", "Plain + self-training: one Noisy Student round from plain, targets "
                      "0.5 P_tta + 0.5 M (fusion mix) -- a departure from the two stages"),
    "bootstrap": ({"bootstrap_beta": 0.8}, "voted", "Plain + bootstrapped targets, beta 0.8 -- departs from "
                  "eq:raw-loss"),
    "ignore_band": ({"ignore_band": 0.2}, "agreement", "Plain + ignore band: pixels where 2-4 of 6 prompts agree "
                    "leave the loss -- departs from eq:raw-loss"),
    "soft": ({"soft_targets": True}, "agreement", "Plain + the agreement map as the target -- departs from "
                                                  "eq:raw-loss"),
    "agreement_weight": ({"agreement_weight": 1.0}, "agreement", "Plain + each pixel weighted by |2A - 1|, how "
                         "unanimous its prompts are -- departs from eq:raw-loss"),
    # issue 63: distill's speed settings at equal steps (not a lever: its gain should be nil), and the folding
    # capacity, on the vote and on the reference
    "bf16": ({"precision": "auto", "channels_last": True}, "voted", "Plain in distill's speed settings (bf16 "
             "autocast where the CPU has bf16 units, channels_last) at the same steps -- not a departure"),
    "expand": ({"expand_branches": True}, "voted", "Plain + RepVGG branches, folded at the end of the stage into "
               "the same TinyUNet -- a training-time departure"),
    "ceiling_expand": ({"expand_branches": True}, "reference", "supervised ceiling + RepVGG branches: the "
                       "reference masks, NOT annotation-free"),
    # the HJM gap's flare and underexposed images (docs/student.md): generic photometric cases the augmentation
    # lacked, drawn a priori (a flare in 3 of 10 photometric draws, -2 to +1 stops of exposure), not fitted
    "photometric": ({"augmentation": PHOTOMETRIC}, "voted", "Plain + lens flares and exposure gain in the "
                    f"augmentation (train.augmentation {PHOTOMETRIC}) -- a training-time change, the loss is the "
                    "paper's"),
    "ceiling_photometric": ({"augmentation": PHOTOMETRIC}, "reference", "supervised ceiling + lens flares and "
                            "exposure gain: the reference masks, NOT annotation-free"),
}
#: variants trained on the reference masks (NOT annotation-free) are compared with the ceiling, not with Plain
CEILING = "ceiling"
#: the gains' pooled row: every scored test image, held to the largest group's noise floor
ALL = "all"
#: the taus at which --fit-of-saved scores the test images for :func:`tau_transfer` (a diagnosis only)
TAU_DIAGNOSIS = tuple(round(0.3 + 0.05 * k, 2) for k in range(14))
#: --refine: the Stage-II methods a saved Plain run warm-starts (the paper's method, its budget-matched control)
REFINE = (PROPOSED, CONTINUATION)
#: self-training's fusion (pipeline.training.self_training.fused_targets)
FUSION, FUSION_WEIGHT = "mix", 0.5


def trained_method(variant: str) -> str:
    """The method a variant trains: the supervised ceiling (NOT annotation-free) for those on the reference masks,
    Stage I (Plain) for the rest."""
    return SUPERVISED_CEILING if VARIANTS[variant][1] == "reference" else STAGE_ONE


def load_data(artifacts: Path, cfg: Mapping[str, Any], methods: tuple[str, ...] = ()) -> dict:
    """The study data of :func:`benchmarks.study_recipe.load_study_data` (Plain's, the ceiling's and those of
    ``methods``), the agreement-map training data, and the test images' voted masks (the vote's own test IoU)."""
    out = load_study_data(artifacts, cfg, methods=tuple(dict.fromkeys((STAGE_ONE, SUPERVISED_CEILING, *methods))))
    out["agreement"] = load_study_data(artifacts, {**cfg, "soft_targets": True}, methods=(STAGE_ONE,))[STAGE_ONE]
    consensus = open_artifact(catalog.path("consensus", artifacts), "consensus")
    _, test = scored_test_rows(artifacts)
    out["test_voted"] = read_rows(consensus, "voted", test).astype(bool)
    return out


def scores(model, data: Mapping[str, Any], device) -> dict:
    """Test Image IoU at the tau calibrated on the validation images, pooled and per group, and the vote's; and the
    fit: the same model's Image IoU on its own TRAINING images against their reference masks (which only score)."""
    vp = predict_probs(model, data["val"].images, device=device, precision="fp32")
    tau, _ = calibrate_threshold(vp, data["val"].masks, EPOCH_TAU_GRID)
    tp = predict_probs(model, data["test_images"], device=device, precision="fp32")
    pred = mask_from_probs(tp, tau)
    ious = image_ious(pred, data["test_masks"])
    # a DEPARTURE screened beside the paper's single tau, never what the document's verdicts score: a threshold per
    # image from its largest probability, calibrated on the same validation masks (docs/student.md)
    relative = calibrate_relative_threshold(vp, data["val"].masks)
    vote = image_ious(data["test_voted"], data["test_masks"])
    groups = data["test_groups"]
    train = data[SUPERVISED_CEILING]  # the training images with their reference masks, in the vote's order
    fit = image_ious(mask_from_probs(predict_probs(model, train.images, device=device, precision="fp32"), tau),
                     np.asarray(train.mask).astype(bool))
    return {"tau_cal": float(tau), "iou_cal": float(ious.mean()), "image_ious": [float(v) for v in ious],
            "groups": {g: float(ious[groups == g].mean()) for g in dict.fromkeys(groups)},
            "vote_groups": {g: float(vote[groups == g].mean()) for g in dict.fromkeys(groups)},
            "train_ious": [float(v) for v in fit],
            "relative_rule": relative,
            "image_ious_relative": [float(v) for v in image_ious(masks_from_relative(tp, relative), data["test_masks"])],
            **({"test_region_counts": error_counts(pred, data["test_masks"], data["test_voted"],
                                                   data["test_regions"]).tolist(),
                # a DIAGNOSIS of the threshold's transfer, never a choice: test IoU per group at each tau of
                # TAU_DIAGNOSIS (picking tau on the test images would be test leakage)
                "test_tau_curve": tau_curve(tp, data["test_masks"], groups)}
               if "test_regions" in data else {})}


def tau_curve(probs: np.ndarray, masks: np.ndarray, groups: np.ndarray) -> dict[str, list[float]]:
    """{group: mean Image IoU at each tau of :data:`TAU_DIAGNOSIS`}: each threshold scored once over every image."""
    ious = np.stack([image_ious(mask_from_probs(probs, t), masks) for t in TAU_DIAGNOSIS])  # [taus, images]
    return {g: [float(row[groups == g].mean()) for row in ious] for g in dict.fromkeys(groups)}


def tau_transfer(doc: Mapping[str, Any]) -> dict[str, dict[str, float]]:
    """A DIAGNOSIS, not a method: per test group, the seeds' mean test IoU at their calibrated tau and at the
    single tau of :data:`TAU_DIAGNOSIS` that is best on the test images (an oracle), each also as a share of the
    vote's IoU there; from :func:`fit_of_saved`'s ``test_tau_curve``.  How much of the gap to the vote is the
    threshold's transfer from the validation images."""
    runs = list(doc["runs"].values())
    out = {}
    for g, vote in runs[0]["vote_groups"].items():
        curve = np.mean([r["test_tau_curve"][g] for r in runs], axis=0)
        k = int(np.argmax(curve))
        cal = float(np.mean([r["groups"][g] for r in runs]))
        out[g] = {"calibrated_taus": [r["tau_cal"] for r in runs], "calibrated": cal, "calibrated_of_vote": cal / vote,
                  "oracle_tau": float(TAU_DIAGNOSIS[k]), "oracle": float(curve[k]), "oracle_of_vote": float(curve[k]) / vote}
    return out


def region_deficit(doc: Mapping[str, Any], groups: np.ndarray, seeds: list[str]) -> dict[str, dict[str, dict]]:
    """Where the student loses to the vote on the test images: per group and region
    (:data:`benchmarks.memorisation.REGIONS`), the pixels per image it gets wrong where the vote is right (``own``),
    those it gets right where the vote is wrong (``corrected``) and ``net`` = own − corrected, means over ``seeds``
    of ``doc``'s runs (their ``test_region_counts``, :func:`fit_of_saved`)."""
    counts = np.mean([np.asarray(doc["runs"][s]["test_region_counts"], np.float64) for s in seeds], axis=0)
    vote_wrong, copied, _, own_wrong = np.moveaxis(counts, -1, 0)  # the COUNTS, in their order
    out = {}
    for g in dict.fromkeys(groups):
        sel = groups == g
        own, corrected = own_wrong[sel].mean(0), (vote_wrong - copied)[sel].mean(0)
        out[str(g)] = {r: {"own": float(own[k]), "corrected": float(corrected[k]), "net": float(own[k] - corrected[k])}
                       for k, r in enumerate(REGIONS)}
    return out


def refined(plain, method: str, cfg: Mapping[str, Any], data: Mapping[str, Any], seed: int, device: str,
            saved: Path):
    """The Stage-II ``method`` (:data:`REFINE`) warm-started from the Plain model ``plain`` of ``seed``: read from
    ``saved``/``<method>-s<seed>.pt`` when a run left it there, else trained here (the method's own epochs and
    targets; the continuation reads Stage I's voted masks) and saved there, so a rerun scores without training."""
    import torch

    path, init = saved / f"{method}-s{seed}.pt", plain.mask_path_state_dict()
    if path.exists():
        model = build_model(get_method(method), cfg, seed, init_state=init)
        model.load_state_dict(torch.load(path, map_location="cpu", weights_only=True))
        return model
    res = training.train(get_method(method), cfg, data[method if method == PROPOSED else STAGE_ONE], data["val"],
                         seed, checkpointer=NoCheckpointer(), init_state=init, device=device, show_progress=False)
    save_model(res.model, path)
    return res.model


def save_model(model, path: Path) -> None:
    """Write ``model``'s weights to ``path`` atomically: a killed run leaves no half-written model to be read as
    done (a saved model is reused, not retrained)."""
    import torch

    with atomic_path(path) as tmp:
        torch.save(model.state_dict(), tmp)


def by_hard_case(doc: Mapping[str, Any], artifacts: Path, variant: str = "plain"
                 ) -> dict[str, dict[str, dict[str, float]]]:
    """Where the student's test images lose, by the synthetic benchmark's image-only degradation (the manifest's
    ``hard_case``: none, glare, flare, underexposed, noise, blur): per group and case, the images, the seeds' mean
    test Image IoU of ``doc``'s runs (a :func:`fit_of_saved` document, or the ``variant`` runs of a runs or
    :func:`combine` document) and the vote's on the same images, and, where the runs kept them
    (``test_region_counts``, a fit document), the student's own false-positive pixels per image on background where
    the vote is right (else None).  Empty when the manifest has no ``hard_case`` (not the synthetic benchmark)."""
    manifest, test = scored_test_rows(artifacts)
    if "hard_case" not in manifest.df:
        return {}
    rows = manifest.df.iloc[test]
    cases, groups = rows["hard_case"].astype(str).to_numpy(), rows["group"].astype(str).to_numpy()
    vote = image_ious(*vote_and_reference(artifacts, test))
    runs = (list(doc["runs"].values()) if isinstance(doc["runs"], Mapping)
            else [r for r in doc["runs"] if r["variant"] == variant])
    if not runs:
        raise SystemExit(f"past_labels --by-hard-case: no runs of variant {variant} in the document")
    student = np.mean([r["image_ious"] for r in runs], axis=0)
    own_bg = (np.mean([np.asarray(r["test_region_counts"])[:, REGIONS.index("background"), COUNTS.index("own_wrong")]
                       for r in runs], axis=0) if all("test_region_counts" in r for r in runs) else None)
    return {g: {c: {"images": int(k.sum()), "student": float(student[k].mean()), "vote": float(vote[k].mean()),
                    "own_background_px": None if own_bg is None else float(own_bg[k].mean())}
                for c in dict.fromkeys(sorted(cases[groups == g])) for k in [(groups == g) & (cases == c)]}
            for g in dict.fromkeys(groups)}


def vote_and_reference(artifacts: Path, rows: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The voted masks and the reference masks of ``rows`` (manifest rows), as bool arrays."""
    consensus = open_artifact(catalog.path("consensus", artifacts), "consensus")
    reference = open_artifact(catalog.path("reference", artifacts), "reference")
    return read_rows(consensus, "voted", rows).astype(bool), read_rows(reference, "mask", rows).astype(bool)


def vote_by_hard_case(artifacts: Path) -> dict[str, dict[str, dict[str, float]]]:
    """What the student's only label says on each degradation: the vote against the reference masks on the training
    and on the scored test images, per split and the manifest's ``hard_case``: the images, the vote's mean Image IoU,
    and its pixels per image marked spacecraft that are not (``too_many_px``) and missed (``missed_px``).  Empty when
    the manifest has no ``hard_case`` (not the synthetic benchmark)."""
    manifest, test = scored_test_rows(artifacts)
    if "hard_case" not in manifest.df:
        return {}
    reference = open_artifact(catalog.path("reference", artifacts), "reference")
    train = np.flatnonzero((manifest.df["split"] == "train").to_numpy())
    out = {}
    for split, rows in (("train", train[read_rows(reference, "has_mask", train).astype(bool)]), ("test", test)):
        vote, ref = vote_and_reference(artifacts, rows)
        cases, iou = manifest.df["hard_case"].to_numpy()[rows].astype(str), image_ious(vote, ref)
        out[split] = {c: {"images": int(k.sum()), "vote": float(iou[k].mean()),
                          "too_many_px": float((vote[k] & ~ref[k]).sum((1, 2)).mean()),
                          "missed_px": float((ref[k] & ~vote[k]).sum((1, 2)).mean())}
                      for c in sorted(set(cases)) for k in [cases == c]}
    return out


def fit_of_saved(artifacts: Path, cfg: Mapping[str, Any], seeds: list[int], device: str,
                 saved: Path | None = None, refine: str | None = None, variant: str = "plain") -> dict:
    """Plain reaches its labels? The saved ``<variant>-s<seed>.pt`` runs (in ``saved``, else beside ``artifacts``;
    ``variant`` one of :data:`VARIANTS`, Plain by default; a ceiling's fit is that of the masks it trained on, NOT
    annotation-free, and a document pair of Plain and the ceiling at the same steps gives the label cost)
    scored on their own TRAINING images against the reference masks, paired per seed and image with the vote's IoU
    there (the seed-aware t interval, clusters = spacecraft; :func:`pipeline.stats.paired_seed_image_t`).  Each
    seed's per-image scores (:func:`scores`) are kept, so that :func:`compare_fits` can pair two such documents;
    with them each test image's error counts per region against the vote
    (:func:`benchmarks.memorisation.error_counts`).  With ``refine`` (a :data:`REFINE` method) each saved Plain
    run warm-starts that Stage-II method (:func:`refined`) and the document scores the refined model instead."""
    import torch

    saved = Path(saved) if saved is not None else artifacts.parent
    trained = trained_method(variant)
    if refine and trained != STAGE_ONE:
        raise SystemExit(f"past_labels --refine: Stage II warm-starts from Plain's Stage I, not from {variant!r}")
    data = load_data(artifacts, cfg, (refine,) if refine else ())
    side = int(np.asarray(data["test_masks"]).shape[-1])
    data["test_regions"] = region_labels(data["test_masks"], data["test_voted"], band_px(side), thin_radius(side))
    train = data[SUPERVISED_CEILING]
    gt = np.asarray(train.mask).astype(bool)
    vote = image_ious(np.asarray(data[STAGE_ONE].mask).astype(bool), gt)
    clusters = train_spacecraft(artifacts)
    if len(clusters) != len(vote):
        raise SystemExit("past_labels: the training images are not the manifest's train rows")
    runs = {}
    for s in seeds:
        model = build_model(get_method(trained), cfg, s)
        model.load_state_dict(torch.load(saved / f"{variant}-s{s}.pt", map_location="cpu", weights_only=True))
        if refine:
            model = refined(model, refine, cfg, data, s, device, saved)
        runs[s] = scores(model.eval(), data, device)
    t, c = np.stack([runs[s]["train_ious"] for s in seeds]), np.stack([vote] * len(seeds))
    iv = paired_seed_image_t(t, c, clusters, 0.95)
    gain = float(np.mean(t - c))
    return {"seeds": seeds, "images": len(vote), "saved": str(saved), "method": refine or trained, "variant": variant,
            "plain": {str(s): float(np.mean(r["train_ious"])) for s, r in runs.items()},
            "vote": float(vote.mean()), "plain_minus_vote": gain, "low": float(iv.low), "high": float(iv.high),
            "verdict": claim_status(gain, float(iv.low), float(iv.high), None, n_seeds=len(seeds)),
            "vote_train_ious": [float(v) for v in vote], "runs": {str(s): r for s, r in runs.items()},
            "host": host_record(),
            "what": "Image IoU on the training images against their reference masks (score only), Plain at its "
                    "calibrated tau; teacher = the synthetic benchmark's SIMULATOR"}


def paired_row(name: str, other: np.ndarray, base: np.ndarray, clusters: np.ndarray, floor: Mapping[str, float],
               seeds, ci: float = 0.95) -> dict:
    """One row of ``other`` − ``base`` [seeds, images], paired by seed and image (the seed-aware t interval,
    clusters = spacecraft), its verdict held to ``floor[name]`` (else the largest floor; none: the interval alone)."""
    iv = paired_seed_image_t(other, base, clusters, ci)
    gain = float(np.mean(other - base))
    g_floor = floor.get(name, max(floor.values(), default=None))
    return {"images": name, "seeds": [int(s) for s in seeds], "base": float(base.mean()), "other": float(other.mean()),
            "other_of_base": float(other.mean() / base.mean()), "gain": gain, "low": float(iv.low),
            "high": float(iv.high), "noise_floor": g_floor,
            "verdict": claim_status(gain, float(iv.low), float(iv.high), g_floor, n_seeds=len(other))}


def relative_tau_gain(doc: Mapping[str, Any], artifacts: Path, floor: Mapping[str, float] | None = None,
                      ci: float = 0.95) -> list[dict]:
    """A SCREEN of a departure: each test group's Image IoU with a threshold per image
    (:func:`pipeline.thresholds.masks_from_relative`, calibrated on the validation images) against the same runs at
    their single calibrated tau, paired by seed and image (:func:`paired_row`), from :func:`fit_of_saved`'s runs;
    ``other_of_vote`` the relative rule's share of the vote."""
    seeds = sorted(doc["runs"], key=int)
    groups, craft = test_column(artifacts, "group"), test_column(artifacts, "spacecraft")
    rows = []
    for name in [*dict.fromkeys(groups), ALL]:
        sel = np.ones(len(groups), bool) if name == ALL else groups == name
        rel = np.stack([np.asarray(doc["runs"][s]["image_ious_relative"])[sel] for s in seeds])
        one = np.stack([np.asarray(doc["runs"][s]["image_ious"])[sel] for s in seeds])
        row = paired_row(name, rel, one, craft[sel], dict(floor or {}), seeds, ci)
        if name != ALL:
            vote = float(np.mean([doc["runs"][s]["vote_groups"][name] for s in seeds]))
            row.update(base_of_vote=row["base"] / vote, other_of_vote=row["other"] / vote)
        rows.append(row)
    return rows


def compare_fits(base: Mapping[str, Any], other: Mapping[str, Any], artifacts: Path,
                 floor: Mapping[str, float] | None = None, ci: float = 0.95) -> dict:
    """``other`` − ``base``, two :func:`fit_of_saved` documents of the same artifacts (say, Plain at 1x and at 2x
    the optimizer steps), paired by their common seeds and by image: on the training images' fit and on the test
    images (the seed-aware t interval, clusters = spacecraft); and each document's fit against the vote and test
    IoU per group as a share of the vote's, with its interval over the seeds (the moonshot's readout;
    :func:`pipeline.report.dvc_results.distillation_efficiency`, NaN at one seed); and, where both documents hold
    them, each side's :func:`region_deficit` (where on the test images it loses to the vote).  A verdict clears the noise floor ``floor``
    {group: IoU} where given (the training images and every test image: its largest), else the interval alone
    decides; one seed holds no seed noise, and its verdict says so (:func:`pipeline.stats.claim_status`)."""
    floor = dict(floor or {})
    seeds = sorted(set(base["runs"]) & set(other["runs"]), key=int)
    if not seeds:
        raise SystemExit("past_labels --compare-fits: the two documents share no seed")
    groups, craft = test_column(artifacts, "group"), test_column(artifacts, "spacecraft")
    where = {"train": ("train_ious", train_spacecraft(artifacts), np.ones(len(base["vote_train_ious"]), bool)),
             **{g: ("image_ious", craft, groups == g) for g in dict.fromkeys(groups)},
             ALL: ("image_ious", craft, np.ones(len(groups), bool))}
    rows = [paired_row(name, np.stack([np.asarray(other["runs"][s][key])[sel] for s in seeds]),
                       np.stack([np.asarray(base["runs"][s][key])[sel] for s in seeds]), clusters[sel], floor, seeds, ci)
            for name, (key, clusters, sel) in where.items()]

    def of_vote(doc):  # {group: (ratio, low, high)}, the report's distillation efficiency over the seeds
        rs = [doc["runs"][s] for s in seeds]
        return {g: distillation_efficiency(float(np.mean(m := [r["groups"][g] for r in rs])),
                                           float(np.std(m, ddof=1)) if len(m) > 1 else float("nan"), len(m),
                                           rs[0]["vote_groups"][g], ci)
                for g in rs[0]["groups"]}

    sides = {"base": of_vote(base), "other": of_vote(other)}
    return {"seeds": [int(s) for s in seeds], "gains": rows,
            **{f"{side}_of_vote": {g: r[0] for g, r in v.items()} for side, v in sides.items()},
            "of_vote_interval": {side: {g: [r[1], r[2]] for g, r in v.items()} for side, v in sides.items()},
            **({"regions": {side: region_deficit(doc, groups, seeds) for side, doc in (("base", base), ("other", other))}}
               if all("test_region_counts" in d["runs"][s] for d in (base, other) for s in seeds) else {}),
            "fit_minus_vote": {"base": {k: base[k] for k in ("plain_minus_vote", "low", "high", "verdict")},
                               "other": {k: other[k] for k in ("plain_minus_vote", "low", "high", "verdict")}},
            "what": "other - base, Plain's Image IoU at its calibrated tau, paired by seed and image; the train row "
                    "scores the training images against their reference masks (score only); teacher = the "
                    "synthetic benchmark's SIMULATOR"}


_DATA: dict = {}


def _init_worker(artifacts: str, cfg: dict, threads: int) -> None:
    import torch

    torch.set_num_threads(threads)
    _DATA.update(load_data(Path(artifacts), cfg))


def _train_data(job: Mapping[str, Any]):
    """The variant's training data; ``self_training`` relabels with the ``plain`` run's saved model."""
    import torch

    kind = VARIANTS[job["variant"]][1]
    if kind == "reference":
        return _DATA[SUPERVISED_CEILING], 0
    if kind == "agreement":
        return _DATA["agreement"], 0
    data = _DATA[STAGE_ONE]
    if kind == "voted":
        return data, 0
    saved = Path(job["saved"]) / f"plain-s{job['seed']}.pt"
    if not saved.exists():
        raise RuntimeError(f"{saved}: run variant plain at seed {job['seed']} first")
    model = build_model(get_method(STAGE_ONE), job["cfg"], job["seed"])
    model.load_state_dict(torch.load(saved, weights_only=True))
    probs = flip_tta_probs(model, data.images, device=job["device"])
    return data.subset(np.arange(len(data)), mask=fused_targets(probs, np.asarray(data.mask), FUSION,
                                                                FUSION_WEIGHT)), len(data) * TTA_PASSES


def _trained(job: Mapping[str, Any], method: str, data):
    """(model, steps run, stop reason, validation curve, where it came from): trained here, or the run of
    ``job["imported"]``, a folder of :mod:`benchmarks.memorisation` (``final.pt``, ``done.json``) trained with the
    same recipe, data and seed."""
    import torch

    if job.get("imported"):
        run = Path(job["imported"])
        record = json.loads((run / "done.json").read_text())
        if (record["method"], record["seed"]) != (method, job["seed"]):
            raise ValueError(f"{run}: a run of {record['method']} seed {record['seed']}, not {method} {job['seed']}")
        model = build_model(get_method(method), job["cfg"], job["seed"])
        model.load_state_dict(torch.load(run / "final.pt", map_location="cpu", weights_only=True))
        curve = [float("nan") if v is None else float(v) for v in record["val_iou_cal"]]
        return (model.eval(), record["steps_run"], record["stopped"], curve,
                f"benchmarks.memorisation run {run.name} at commit {record['commit']}")
    resume = resume_dir(job)
    if (resume / RESUME_STATE_FILE).exists():
        print(f"  {job['variant']} s{job['seed']}: resuming from {resume}", flush=True)
    res = training.train(get_method(method), job["cfg"], data, _DATA["val"], job["seed"],
                         checkpointer=FileCheckpointer(resume), device=job["device"], show_progress=False,
                         callback=_progress(job))
    return (res.model, res.info["steps_run"], res.info.get("stopped"), [float(v) for v in res.log["val_iou_cal"]],
            "trained here")


def resume_dir(job: Mapping[str, Any]) -> Path:
    """The folder of a job's per-epoch resume state: ``<saved>/resume/<variant>-s<seed>``.  A run killed midway (a
    session's end, a reboot) resumes there after its last epoch, with the same weights as a run never stopped
    (:func:`pipeline.training.loop.train`; the state names its run key, so other settings start afresh); the
    state is removed once the run is scored and saved."""
    return Path(job["saved"]) / "resume" / f"{job['variant']}-s{job['seed']}"


def _progress(job: Mapping[str, Any]):
    """A training callback printing every tenth of Stage I's epochs: a study of hours says where it is."""
    total = int(job["cfg"].get("epochs_stage1") or 0)
    every = max(1, total // 10)

    def show(epoch: int, row: Mapping[str, Any]) -> None:
        if epoch % every == 0:
            loss = row.get("loss", float("nan"))
            print(f"  {job['variant']} s{job['seed']}: epoch {epoch}/{total or '?'}, loss {loss:.4f}", flush=True)

    return show


def run_one(job: dict) -> dict:
    """Train one (variant, seed), or import its run, and score it."""

    t0 = time.perf_counter()
    data, relabel = _train_data(job)
    method = trained_method(job["variant"])
    model, steps, stopped, curve, source = _trained(job, method, data)
    # plain's: self-training's starting point; each (the ceiling's too, NOT annotation-free): --fit-of-saved
    save_model(model, Path(job["saved"]) / f"{job['variant']}-s{job['seed']}.pt")
    out = {"variant": job["variant"], "method": job["method"], "trained": method, "seed": job["seed"],
           "steps_run": steps, "stopped": stopped, "images_seen": int(steps) * int(job["cfg"]["batch_size"]),
           "relabel_passes": relabel, "n_train": len(data), "val_iou_cal_curve": curve, "source": source,
           "host": host_record()}  # per run: a resumed study may finish on another CPU (docs/stability.md)
    out.update(scores(model, _DATA, job["device"]))
    out["seconds"] = time.perf_counter() - t0  # this process's share: a resumed run's earlier epochs are not in it
    state = resume_dir(job) / RESUME_STATE_FILE
    if state.exists():  # this run's own state, written by its training above
        state.unlink()
        if not any(state.parent.iterdir()):
            state.parent.rmdir()
    print(f"  done {job['variant']:14s} s{job['seed']}: test IoU {out['iou_cal']:.3f} {out['groups']} "
          f"({out['steps_run']} steps, {out['seconds']:.0f} s)", flush=True)
    return out


def cost(run: Mapping[str, Any], runs: Mapping[tuple, Mapping[str, Any]]) -> float:
    """Training images seen plus weighted relabelling passes, self-training's ``plain`` round included."""
    own = run["images_seen"] + RELABEL_WEIGHT * run["relabel_passes"]
    if run["variant"] == "self_training":
        own += runs[("plain", run["seed"])]["images_seen"]
    return float(own)


def summarize(results: list[dict]) -> list[dict]:
    """Per variant: mean test IoU per group over seeds, the ratio to the ceiling and to the vote, the cost."""
    by = {(r["variant"], r["seed"]): r for r in results}
    rows = []
    for v in dict.fromkeys(r["variant"] for r in results):
        rs = [r for r in results if r["variant"] == v]
        groups = list(rs[0]["groups"])
        row = {"variant": v, "n_seeds": len(rs), "iou_cal": float(np.mean([r["iou_cal"] for r in rs])),
               "groups": {g: float(np.mean([r["groups"][g] for r in rs])) for g in groups},
               "vote_groups": rs[0]["vote_groups"],
               "cost": float(np.mean([cost(r, by) for r in rs if v != "self_training" or ("plain", r["seed"]) in by]
                                     or [float("nan")]))}
        rows.append(row)
    ceiling = next((r for r in rows if r["variant"] == CEILING), None)
    for r in rows:
        r["of_vote"] = {g: r["groups"][g] / r["vote_groups"][g] for g in r["groups"]}
        if ceiling is not None:
            r["of_ceiling"] = {g: r["groups"][g] / ceiling["groups"][g] for g in r["groups"]}
    return rows


def test_column(artifacts: Path, column: str) -> np.ndarray:
    """A manifest column (``group``, ``spacecraft``) of each scored test image, in the order of a run's
    ``image_ious`` (:func:`load_data`)."""
    manifest, test = scored_test_rows(artifacts)
    return manifest.df[column].to_numpy()[test].astype(str)


def overlay(base: Mapping[str, Any], changes: Mapping[str, Any]) -> dict:
    """``base`` with a variant's ``changes``; a mapping value (a sub-section, ``augmentation``) merges into
    ``base``'s instead of replacing it."""
    return {**base, **{k: {**base[k], **v} if isinstance(v, Mapping) else v for k, v in changes.items()}}


def train_spacecraft(artifacts: Path) -> np.ndarray:
    """The spacecraft of each training image, in the order of a run's ``train_ious`` (the manifest's train rows)."""
    manifest = open_artifact(catalog.path("manifest", artifacts), "manifest").df
    return manifest["spacecraft"].to_numpy()[(manifest["split"] == "train").to_numpy()].astype(str)


def gains(runs: list[dict], spacecraft: np.ndarray, groups: np.ndarray, floor: Mapping[str, float],
          control: str = "plain", ci: float = 0.95) -> list[dict]:
    """Each variant minus ``control`` per test group, paired by seed and image: the seed-aware t interval
    (:func:`pipeline.stats.paired_seed_image_t`, the effect on these spacecraft) and the signed verdict against the
    noise floor ``floor`` {group: IoU} (:func:`pipeline.stats.claim_status`), then the same over every test image
    (:data:`ALL`, against the largest floor).  A variant trained on the reference masks is compared with
    :data:`CEILING` instead."""
    by = {(r["variant"], r["seed"]): np.asarray(r["image_ious"]) for r in runs}
    out = []
    for v in dict.fromkeys(r["variant"] for r in runs):
        base = CEILING if VARIANTS[v][1] == "reference" else control
        seeds = sorted(s for (w, s) in by if w == v and (base, s) in by)
        if v == base or not seeds:
            continue
        # per group, then every test image (ALL), held to the largest group floor
        for g in [*dict.fromkeys(groups), ALL]:
            sel = np.ones(len(groups), bool) if g == ALL else groups == g
            g_floor = max(floor.values(), default=None) if g == ALL else floor.get(str(g))
            t = np.stack([by[(v, s)][sel] for s in seeds])
            c = np.stack([by[(base, s)][sel] for s in seeds])
            iv = paired_seed_image_t(t, c, spacecraft[sel], ci)
            gain, lo, hi = float(np.mean(t - c)), float(iv.low), float(iv.high)
            out.append({"variant": v, "control": base, "group": str(g), "seeds": seeds, "gain": gain, "low": lo,
                        "high": hi, "noise_floor": g_floor,
                        "verdict": claim_status(gain, lo, hi, g_floor, n_seeds=len(seeds))})
    return out


def noise_floor(path: Path, key: str) -> dict[str, float]:
    """{group: Plain's test-IoU noise floor} of record ``key`` (``<recipe>@<profile>-<resolution>``) in
    reports/noise_floor.json; empty when it is not measured there."""
    doc = json.loads(path.read_text()) if path.is_file() else {}
    numbers = (doc.get("recipes", {}).get(key) or {}).get("numbers", {})
    return {k.split("/")[1]: float(v["floor"]) for k, v in numbers.items()
            if k.startswith(f"{STAGE_ONE}/") and k.endswith("/iou")}


def _runs_document(path: Path) -> dict:
    """An output file of this benchmark, or the runs it has finished so far (its ``.runs.jsonl``)."""
    if not path.name.endswith(".runs.jsonl"):
        return json.loads(path.read_text())
    lines = [json.loads(x) for x in path.read_text().splitlines() if x.strip()]
    runs = lines[1:]
    return {"info": lines[0]["info"] if lines else {}, "runs": runs,
            "variants": {r["variant"]: {"overrides": VARIANTS[r["variant"]][0], "what": VARIANTS[r["variant"]][2]}
                         for r in runs}}


def combine(paths: list[Path], floor_key: str, floors: Path) -> dict:
    """One document from several runs files of this benchmark on the same artifacts: every run, the summary per
    variant (:func:`summarize`) and each variant's paired gain over Plain (:func:`gains`)."""
    docs = [_runs_document(Path(p)) for p in paths]
    docs = [d for d in docs if d["runs"]]
    artifacts = {d["info"]["artifacts"] for d in docs}
    if len(artifacts) != 1:
        raise ValueError(f"runs on different artifacts: {sorted(artifacts)}")
    runs = list({(r["variant"], r["seed"]): r for d in docs for r in d["runs"]}.values())
    art = Path(artifacts.pop())
    manifest, test = scored_test_rows(art)
    groups = manifest.df["group"].to_numpy()[test].astype(str)
    floor = noise_floor(floors, floor_key)
    return {"info": {**docs[0]["info"], "combined_from": [str(p) for p in paths], "noise_floor_key": floor_key,
                     "noise_floor": floor},
            "variants": {k: v for d in docs for k, v in d["variants"].items()},
            "relabel_weight": RELABEL_WEIGHT, "summary": summarize(runs),
            "gains": gains(runs, test_column(art, "spacecraft"), groups, floor), "runs": runs}


def table(doc: Mapping[str, Any]) -> str:
    """Markdown: per variant its test IoU per group, of the ceiling and of the vote, cost; then the gains."""
    rows = doc["summary"]
    groups = list(rows[0]["groups"])
    head = ("| variant | seeds | " + " | ".join(f"{g} IoU" for g in groups) + " | of ceiling | of vote | cost |\n|"
            + "---|" * (len(groups) + 5))
    lines = [head]
    for r in rows:
        ratio = (lambda d: " / ".join(f"{d[g]:.2f}" for g in groups))
        lines.append(f"| {r['variant']} | {r['n_seeds']} | " + " | ".join(f"{r['groups'][g]:.3f}" for g in groups)
                     + f" | {ratio(r['of_ceiling']) if 'of_ceiling' in r else '--'} | {ratio(r['of_vote'])} | "
                     f"{r['cost']:,.0f} |")
    lines += ["", "| lever - its control | group | seeds | gain [95 % CI] | noise floor | verdict |",
              "|---|---|---|---|---|---|"]
    for g in doc["gains"]:
        floor = "--" if g["noise_floor"] is None else f"{g['noise_floor']:.3f}"
        lines.append(f"| {g['variant']} - {g.get('control', 'plain')} | {g['group']} | {len(g['seeds'])} | {g['gain']:+.3f} [{g['low']:+.3f}, "
                     f"{g['high']:+.3f}] | {floor} | {g['verdict']} |")
    return "\n".join(lines)


def fits_table(doc: Mapping[str, Any]) -> str:
    """Markdown of :func:`compare_fits`: the paired gains, then each side's test IoU as a share of the vote's."""
    lines = ["| images | seeds | base | other | other / base | other - base [95 % CI] | noise floor | verdict |",
             "|---|---|---|---|---|---|---|---|"]
    lines += [f"| {r['images']} | {len(r['seeds'])} | {r['base']:.3f} | {r['other']:.3f} | "
              f"{r['other'] / r['base']:.3f} | {r['gain']:+.3f} "
              f"[{r['low']:+.3f}, {r['high']:+.3f}] | "
              f"{'--' if r['noise_floor'] is None else format(r['noise_floor'], '.3f')} | {r['verdict']} |"
              for r in doc["gains"]]
    groups = list(doc["base_of_vote"])
    lines += ["", "| of the vote | " + " | ".join(groups) + " |", "|---|" + "---|" * len(groups)]
    ivs = doc.get("of_vote_interval", {})  # documents written before the intervals have none
    lines += [f"| {side} | " + " | ".join(f"{doc[side + '_of_vote'][g]:.2f}" + (
        " [{:.2f}, {:.2f}]".format(*ivs[side][g]) if side in ivs else "") for g in groups) + " |"
              for side in ("base", "other")]
    if "regions" in doc:
        lines += ["", "| test pixels per image the student gets wrong where the vote is right, less those it corrects "
                  "| " + " | ".join(REGIONS) + " | total |", "|---|" + "---|" * (len(REGIONS) + 1)]
        lines += [f"| {side} {g} | " + " | ".join(f"{by[r]['net']:+.1f}" for r in REGIONS)
                  + f" | {sum(v['net'] for v in by.values()):+.1f} |"
                  for side in ("base", "other") for g, by in doc["regions"][side].items()]
    return "\n".join(lines)


def main(argv=None) -> dict:
    ap = parser(__doc__, artifacts=None, workdir="past_labels", profile="reduced", resolution=64, epochs=None,
                seeds=[42], device="cpu", jobs=1, threads=2, out="past_labels.json", set=[])
    add_data_size_options(ap)
    ap.add_argument("--variants", nargs="+", default=list(VARIANTS), choices=list(VARIANTS))
    ap.add_argument("--import-run", nargs=2, action="append", default=[], metavar=("VARIANT", "DIR"),
                    help="score the run in DIR (benchmarks.memorisation's final.pt and done.json, same recipe, "
                         "data and seed) as VARIANT (plain or ceiling) instead of training it again")
    ap.add_argument("--combine", nargs="+", type=Path, default=None, metavar="RUNS_JSON",
                    help="write one document (--out) from these output files of this benchmark (same artifacts): "
                         "their runs, the summary and each lever's gain over Plain; nothing trains")
    ap.add_argument("--noise-floor", type=Path, default=Path("reports/noise_floor.json"))
    ap.add_argument("--fit-of-saved", action="store_true",
                    help="train nothing: score the saved plain-s<seed>.pt beside the artifacts on their own training "
                         "images against the vote's fit there (:func:`fit_of_saved`)")
    ap.add_argument("--refine", choices=REFINE, default=None,
                    help="--fit-of-saved: warm-start this Stage-II method from each saved Plain run (trained once, "
                         "saved beside it as <method>-s<seed>.pt) and score it instead (:func:`refined`)")
    ap.add_argument("--saved-dir", type=Path, default=None,
                    help="where each variant's trained <variant>-s<seed>.pt go (plain's: "
                         "self-training's start) and --fit-of-saved reads them (default: beside the artifacts; give "
                         "each step budget its own, or a run replaces another's)")
    ap.add_argument("--saved-variant", default="plain",
                    choices=list(VARIANTS),
                    help="--fit-of-saved: the variant whose saved runs it scores (a ceiling's: NOT annotation-free; "
                         "with a Plain document at the same steps, --compare-fits gives the label cost); "
                         "--by-hard-case: the variant it reads from a runs or --combine document (default: plain)")
    ap.add_argument("--floor-key", default=None,
                    help="--compare-fits: the noise floor record (<recipe>@<profile>-<resolution>) its verdicts "
                         "clear (default: this run's own)")
    ap.add_argument("--by-hard-case", type=Path, default=None, metavar="FIT_JSON",
                    help="train nothing: a --fit-of-saved output's test images by the benchmark's degradation "
                         "(:func:`by_hard_case`), with --artifacts")
    ap.add_argument("--compare-fits", nargs=2, type=Path, default=None, metavar=("BASE_JSON", "OTHER_JSON"),
                    help="train nothing: OTHER - BASE, two --fit-of-saved outputs of the same artifacts "
                         "(--artifacts), paired by seed and image (:func:`compare_fits`)")
    args = ap.parse_args(argv)
    # the noise floor record of this run's configuration (reports/noise_floor.json)
    own_key = f"{load_profile(args.profile, args.sets)['train']['recipe']}@{args.profile}-{args.resolution}"
    if args.by_hard_case:
        if not args.artifacts:
            ap.error("--by-hard-case needs --artifacts (the runs' artifacts)")
        doc = {"fit": str(args.by_hard_case), "variant": args.saved_variant,
               "groups": by_hard_case(json.loads(args.by_hard_case.read_text()), Path(args.artifacts),
                                      args.saved_variant),
               "vote": vote_by_hard_case(Path(args.artifacts))}
        Path(args.out).write_text(json.dumps(doc, indent=1))
        print("| group | degradation | images | student | vote | student - vote | own background px per image |\n"
              "|---|---|---|---|---|---|---|")
        for g, by in doc["groups"].items():
            for c, v in by.items():
                print(f"| {g} | {c} | {v['images']} | {v['student']:.3f} | {v['vote']:.3f} | "
                      f"{v['student'] - v['vote']:+.3f} | "
                      f"{'--' if v['own_background_px'] is None else format(v['own_background_px'], '.0f')} |")
        print("\n| split | degradation | images | the vote's IoU | px too many | px missed |\n|---|---|---|---|---|---|")
        for split, by in doc["vote"].items():
            for c, v in by.items():
                print(f"| {split} | {c} | {v['images']} | {v['vote']:.3f} | {v['too_many_px']:.0f} | "
                      f"{v['missed_px']:.0f} |")
        return doc
    if args.compare_fits:
        if not args.artifacts:
            ap.error("--compare-fits needs --artifacts (the runs' artifacts)")
        base, other = (json.loads(Path(p).read_text()) for p in args.compare_fits)
        key = args.floor_key or own_key
        doc = {**compare_fits(base, other, Path(args.artifacts), noise_floor(args.noise_floor, key)),
               "noise_floor_key": key}
        Path(args.out).write_text(json.dumps(doc, indent=1))
        print(fits_table(doc))
        return doc
    if args.combine:
        doc = combine(args.combine, own_key, args.noise_floor)
        Path(args.out).write_text(json.dumps(doc, indent=1))
        print(table(doc))
        return doc
    imported = dict(args.import_run)
    if set(imported) - {"plain", CEILING}:
        ap.error("--import-run: only plain and ceiling runs can be imported")
    device = str(resolve_device(args.device))
    sets = [f"data.resolution={args.resolution}", "protocol.supervised_ceiling=true"] + data_size_sets(args) + args.sets
    params = load_profile(args.profile, sets)
    artifacts = (Path(args.artifacts) if args.artifacts
                 else build_artifacts(Path(args.workdir).resolve(), args.profile, sets, device))
    base = {**params["train"], "num_threads": args.threads}
    if args.epochs is not None:
        base["epochs_stage1"] = args.epochs
    saved = Path(args.saved_dir) if args.saved_dir else artifacts.parent
    if args.fit_of_saved:
        doc = fit_of_saved(artifacts, overlay(base, VARIANTS[args.saved_variant][0]), args.seeds, device, saved,
                           args.refine, args.saved_variant)
        key = args.floor_key or own_key
        doc["relative_tau"] = {"noise_floor_key": key,
                               "gains": relative_tau_gain(doc, artifacts, noise_floor(args.noise_floor, key))}
        Path(args.out).write_text(json.dumps(doc, indent=1))
        print(f"fit on the training images: {doc['method']} {np.mean(list(doc['plain'].values())):.3f} vs the vote "
              f"{doc['vote']:.3f}: {doc['plain_minus_vote']:+.3f} [{doc['low']:+.3f}, {doc['high']:+.3f}] "
              f"({doc['verdict']})")
        for g, v in tau_transfer(doc).items():
            print(f"{g}: test IoU {v['calibrated']:.3f} at the calibrated tau ({v['calibrated_of_vote']:.2f} of the "
                  f"vote); {v['oracle']:.3f} at tau {v['oracle_tau']:.2f}, the test images' best "
                  f"({v['oracle_of_vote']:.2f}; an oracle, a diagnosis only)")
        for r in doc["relative_tau"]["gains"]:
            print(f"{r['images']}: a threshold per image (a departure, screened): {r['other']:.3f} against "
                  f"{r['base']:.3f}, {r['gain']:+.3f} [{r['low']:+.3f}, {r['high']:+.3f}] ({r['verdict']})"
                  + (f"; {r['other_of_vote']:.2f} of the vote" if "other_of_vote" in r else ""))
        return doc
    saved.mkdir(parents=True, exist_ok=True)
    info = {"artifacts": str(artifacts), "device": device, "resolution": args.resolution, "profile": args.profile,
            "epochs": base["epochs_stage1"], "n_train": None, "recipe": base["recipe"], "seeds": args.seeds,
            "threads": args.threads, "jobs": args.jobs, "simulator": "the teacher is the synthetic benchmark's SIMULATOR"}
    # plain before self_training: a round starts from plain's saved model
    order = sorted(args.variants, key=lambda v: VARIANTS[v][1] == "self_training")
    jobs = [{"variant": v, "method": v, "seed": s, "device": device, "cfg": overlay(base, VARIANTS[v][0]),
             "imported": imported.get(v), "saved": str(saved)} for s in args.seeds for v in order]
    t0 = time.perf_counter()

    def run_all(todo):
        first = [j for j in todo if VARIANTS[j["variant"]][1] != "self_training"]
        yield from run_jobs(first, str(artifacts), base, args.jobs, args.threads, _init_worker, run_one)
        yield from run_jobs([j for j in todo if j not in first], str(artifacts), base, 1, args.threads,
                            _init_worker, run_one)

    done = resumed_runs(args.out, info, jobs, run_all)
    results = [done[(j["variant"], j["method"], j["seed"])] for j in jobs]
    info["wall_seconds"] = time.perf_counter() - t0
    rows = summarize(results)
    for r in rows:
        print(f"{r['variant']:14s} n={r['n_seeds']} IoU {r['iou_cal']:.3f} groups "
              + " ".join(f"{g} {v:.3f}" for g, v in r["groups"].items())
              + (" of ceiling " + " ".join(f"{v:.2f}" for v in r["of_ceiling"].values()) if "of_ceiling" in r else "")
              + " of vote " + " ".join(f"{v:.2f}" for v in r["of_vote"].values()) + f" cost {r['cost']:.0f}")
    out = {"info": info, "variants": {v: {"overrides": VARIANTS[v][0], "what": VARIANTS[v][2]} for v in args.variants},
           "relabel_weight": RELABEL_WEIGHT, "summary": rows, "runs": results}
    Path(args.out).write_text(json.dumps(out, indent=1))
    print(f"wrote {args.out}")
    return out


if __name__ == "__main__":
    main()
