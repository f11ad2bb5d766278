"""Does the per-frame confidence (:func:`pipeline.deploy.confidence.frame_confidence`) rank bad frames?  Per
test group of a run and pooled: Spearman's rho between the deployed student's frame confidence and its Image
IoU against the reference masks, and the mean IoU of the lowest-confidence quarter against the rest.

    python -m benchmarks.frame_confidence --artifacts artifacts [--deploy artifacts/deploy]
"""

from __future__ import annotations

import argparse

import numpy as np

from pipeline import catalog
from pipeline.deploy.confidence import confidence_rank_check
from pipeline.evaluation.inference import open_labelled_split
from pipeline.metrics import image_iou


def frame_scores(artifacts, deploy=None, engine: str = "torch",
                 split: str = "test") -> dict[str, tuple[np.ndarray, np.ndarray]]:
    """``{group: (confidence [n], Image IoU [n])}`` of the deployed student on the run's ``split`` frames."""
    from pipeline.deploy.segmenter import Segmenter

    manifest, images, reference, test = open_labelled_split(artifacts, split, "nothing to score")
    seg = Segmenter.from_bundle(deploy or catalog.path("deploy", artifacts), engine=engine)
    groups = manifest.df["group"].to_numpy()
    out: dict[str, tuple[list, list]] = {}
    for i in test:
        mask, score = seg.predict(np.asarray(images["image"][i]), return_score=True)
        sc, ious = out.setdefault(str(groups[i]), ([], []))
        sc.append(score)
        ious.append(image_iou(mask, np.asarray(reference["mask"][i], bool)))
    return {g: (np.asarray(s, float), np.asarray(v, float)) for g, (s, v) in out.items()}


def rows(scores: dict[str, tuple[np.ndarray, np.ndarray]]) -> list[dict]:
    """One row per group and one pooled: n, rho, p, the mean IoU of the lowest-confidence quarter and the rest's."""
    pooled = (np.concatenate([s for s, _ in scores.values()]), np.concatenate([v for _, v in scores.values()]))
    out = []
    for name, (s, v) in [*scores.items(), ("all", pooled)]:
        r = confidence_rank_check(s, v)
        low = s <= np.quantile(s, 0.25)
        out.append({"group": name, "n": len(s), "rho": r.rho, "p": r.pvalue,
                    "iou_low_quarter": float(v[low].mean()), "iou_rest": float(v[~low].mean()) if (~low).any()
                    else float("nan")})
    return out


def main(argv=None) -> list[dict]:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--artifacts", default=catalog.ARTIFACTS_DIR)
    ap.add_argument("--deploy", default=None, help="deploy bundle (default: the run's, artifacts/deploy)")
    ap.add_argument("--engine", default="torch")
    ap.add_argument("--split", default="test", help="the frames scored (test; val for a run without test masks)")
    args = ap.parse_args(argv)
    table = rows(frame_scores(args.artifacts, args.deploy, args.engine, args.split))
    print(f"{'group':8s} {'frames':>6s} {'rho':>7s} {'p':>9s} {'IoU lowest 25%':>15s} {'IoU rest':>9s}")
    for r in table:
        print(f"{r['group']:8s} {r['n']:6d} {r['rho']:+7.3f} {r['p']:9.2g} {r['iou_low_quarter']:15.3f} "
              f"{r['iou_rest']:9.3f}")
    return table


if __name__ == "__main__":
    main()
