"""What limits the student's fit to its training images: optimizer steps or capacity? (issue 63 item 1)

Collects :mod:`benchmarks.memorisation` runs of Plain (Stage I on the vote, annotation-free) and the supervised
ceiling (the same recipe on the REFERENCE masks; NOT annotation-free) at 1x, 2x and 4x the optimizer steps and at
1.5x the channels (a diagnosis only: the deployed TinyUNet is 24/48/96), each scored on its own TRAINING images
against the reference masks at its calibrated tau.  The runs share the training images, so their differences are
paired per image (bootstrap over the 270 images, 95 % percentile intervals).  One seed: seed-to-seed noise is not in
these intervals; the 64² noise floor (seeds and numerics, 0.020 IoU, docs/student.md) is the yardstick of an effect.

    python -m benchmarks.fit_limit --run 1x=fit/plain-220.json,fit/ceiling-220.json --run 2x=... \
        --out reports/fit/fit-limit-64.json --figure docs/figures/fit-limit-64.png

Each ``--run LABEL=JSON[,JSON...]`` names memorisation outputs; each JSON's run directories hold the per-image
scores (``scores/final.npz``) when ``--workdir-root`` is given, else only the JSON's summaries are used (no pairing).
"""

from __future__ import annotations

import json
import zlib
from pathlib import Path
from typing import Any, Mapping

import numpy as np

from benchmarks.common import parser
from benchmarks.memorisation import BOOTSTRAP_RESAMPLES, bootstrap_mean
from pipeline.artifacts.atomic import write_text_if_changed
from pipeline.stats import NO_DIFFERENCE

#: a paired difference that clears this counts as an effect: the largest noise floor (seeds and numerics) measured
#: at 64² (``plateau@reduced-64`` in reports/noise_floor.json; docs/student.md)
NOISE_FLOOR = 0.020


def _sets(info: Mapping[str, Any]) -> dict[str, str]:
    return dict(s.split("=", 1) for s in info.get("sets", []))


def read_point(label: str, path: Path, workdir_root: Path | None) -> list[dict]:
    """The runs of one memorisation JSON as rows: label, method, epochs, steps, channels, seconds, final IoU against
    the reference at the calibrated tau (with its interval), IoU with the vote, and per-image IoUs where found.

    Parameters
    ----------
    label : str
        The point's name (``1x``, ``2x``, ``1.5x channels``).
    path : Path
        A :mod:`benchmarks.memorisation` JSON.
    workdir_root : Path or None
        Where ``<json stem>/runs/*/<method>-s<seed>/scores/final.npz`` lies; None = no per-image scores.

    Returns
    -------
    list of dict
        One row per run in the JSON.
    """
    doc = json.loads(path.read_text())
    info, sets = doc["info"], _sets(doc["info"])
    rows = []
    for m, r in doc["runs"].items():
        s = r["summary"]["cal"]
        per_image = None
        if workdir_root is not None:
            found = sorted((workdir_root / path.stem).glob(f"runs/*/{m}-s{info['seed']}/scores/final.npz"))
            if found:
                with np.load(found[0], allow_pickle=False) as z:
                    per_image = np.asarray(z["iou_ref_cal"], np.float64).tolist()
        rows.append({"label": label, "method": m, "annotation_free": r["annotation_free"],
                     "epochs": r["epochs_run"], "low_res_epochs": r["low_res_epochs"], "steps": r["steps_run"],
                     "channels": sets.get("train.channels", "[24, 48, 96]"), "seconds": r["seconds"],
                     "commit": r["commit"], "final_iou_ref": s["final"]["iou_ref"], "peak_iou_ref": s["peak"]["iou_ref"],
                     "peak_epoch": s["peak_epoch"], "tau_cal": s["final_tau_cal"],
                     "agreement_with_vote": s["final"]["agreement_with_vote"], "per_image": per_image,
                     "vote_iou_ref": doc["vote"]["iou_ref_ci"]})
    return rows


def paired(a: list[float], b: list[float], rng: np.random.Generator) -> list[float]:
    """Mean of ``b - a`` over images with its 95 % bootstrap interval.

    Parameters
    ----------
    a, b : list of float
        Per-image IoUs of two runs on the same images.
    rng : numpy.random.Generator
        The resampling generator.

    Returns
    -------
    list of float
        ``[mean, lo, hi]``.
    """
    return [round(v, 4) for v in bootstrap_mean(np.asarray(b) - np.asarray(a), rng, BOOTSTRAP_RESAMPLES)]


def verdict(ci: list[float], floor: float = NOISE_FLOOR) -> str:
    """``gain`` / ``loss`` when the interval's bound nearest 0 clears the noise floor, else ``no difference``.

    Parameters
    ----------
    ci : list of float
        ``[mean, lo, hi]``.
    floor : float
        The noise floor.

    Returns
    -------
    str
        The verdict.
    """
    return "gain" if ci[1] > floor else "loss" if ci[2] < -floor else NO_DIFFERENCE


def comparisons(rows: list[dict], base: str, seed: int = 0) -> list[dict]:
    """Each run minus the ``base`` point's run of the same method, paired per image where both have per-image scores.

    Parameters
    ----------
    rows : list of dict
        :func:`read_point` rows.
    base : str
        The label of the reference point (1x).
    seed : int
        The bootstrap seed.

    Returns
    -------
    list of dict
        One comparison per non-base row.
    """
    ref = {r["method"]: r for r in rows if r["label"] == base}
    out = []
    for r in rows:
        b = ref.get(r["method"])
        if r["label"] == base or b is None:
            continue
        c = {"method": r["method"], "label": r["label"], "minus": base,
             "unpaired": round(r["final_iou_ref"][0] - b["final_iou_ref"][0], 4)}
        if r["per_image"] and b["per_image"]:
            # a stream of its own per comparison: its interval does not move when another run is added
            key = zlib.crc32(f"{r['method']}|{r['label']}|{base}".encode())
            c["paired"] = paired(b["per_image"], r["per_image"], np.random.default_rng([seed, key]))
            c["verdict"] = verdict(c["paired"])
        out.append(c)
    return out


def figure(rows: list[dict], path: Path) -> None:
    """Fit against optimizer steps: Plain and the ceiling, 1.5x channels as open markers, the vote as a band.

    Parameters
    ----------
    rows : list of dict
        :func:`read_point` rows.
    path : Path
        The PNG to write.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(6.4, 4.2), dpi=120)
    styles = {"plain": ("#1f77b4", "Plain (vote; annotation-free)"),
              "supervised_ceiling": ("#000000", "Supervised ceiling (REFERENCE masks; NOT annotation-free)")}
    for m, (color, name) in styles.items():
        for wide in (False, True):
            pts = sorted((r["steps"], r["final_iou_ref"]) for r in rows
                         if r["method"] == m and (r["channels"] != "[24, 48, 96]") == wide)
            if not pts:
                continue
            x = [p[0] for p in pts]
            y = [p[1][0] for p in pts]
            err = [[p[1][0] - p[1][1] for p in pts], [p[1][2] - p[1][0] for p in pts]]
            ax.errorbar(x, y, yerr=err, color=color, marker="o", mfc="none" if wide else color,
                        ls="none" if wide else "-", capsize=3,
                        label=f"{name}, 1.5x channels" if wide else name)
    vote = rows[0]["vote_iou_ref"]
    ax.axhspan(vote[1], vote[2], color="#ff7f0e", alpha=0.15)
    ax.axhline(vote[0], color="#ff7f0e", ls="--", label="the vote (SIMULATOR teacher)")
    ax.set_xscale("log", base=2)
    ax.set_xlabel("optimizer steps (Stage I, batch 8)")
    ax.set_ylabel("IoU vs reference, own training images")
    ax.set_title("Fit against steps, 64², progressive, seed 42 (one seed)", fontsize=9)
    ax.legend(fontsize=7, loc="lower right")
    fig.tight_layout()
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, metadata={"Software": None})
    plt.close(fig)


def main(argv=None) -> dict:
    """Collect the runs, compare them with the base point, write the JSON (and the figure).

    Parameters
    ----------
    argv : list of str or None
        Command-line arguments.

    Returns
    -------
    dict
        The JSON document.
    """
    ap = parser(__doc__, out="reports/fit/fit-limit-64.json")
    ap.add_argument("--run", action="append", required=True, metavar="LABEL=JSON[,JSON...]")
    ap.add_argument("--base", default="1x", help="the label the others are compared with")
    ap.add_argument("--workdir-root", default=None, help="where each JSON's memorisation workdir lies (by stem)")
    ap.add_argument("--figure", default=None)
    args = ap.parse_args(argv)
    root = Path(args.workdir_root) if args.workdir_root else None
    rows = []
    for item in args.run:
        label, _, paths = item.partition("=")
        for p in paths.split(","):
            rows += read_point(label, Path(p), root)
    doc = {"info": {"what": "fit of the student to its own training images against optimizer steps and channels "
                            "(issue 63 item 1); teacher SIMULATOR (synthetic benchmark); one seed",
                    "noise_floor": NOISE_FLOOR, "bootstrap": f"{BOOTSTRAP_RESAMPLES} paired resamples of the training images",
                    "base": args.base},
           "runs": rows, "comparisons": comparisons(rows, args.base)}
    write_text_if_changed(Path(args.out), json.dumps(doc, indent=1) + "\n")
    if args.figure:
        figure(rows, Path(args.figure))
    for c in doc["comparisons"]:
        print(f"{c['method']:>20} {c['label']:>16} - {c['minus']}: unpaired {c['unpaired']:+.3f}"
              + (f", paired {c['paired'][0]:+.3f} [{c['paired'][1]:+.3f}, {c['paired'][2]:+.3f}] {c['verdict']}"
                 if "paired" in c else ""))
    return doc


if __name__ == "__main__":
    main()
