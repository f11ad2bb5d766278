"""The opt-in end-to-end check of the Label Studio review loop against a real server (docs/review.md; never in
CI): upload a review export, compare every served image with its file, draw an anti-aliased brush stroke on every
task, export the project and check that ``review import`` gives each image its vote united with the stroke, bit
for bit.  Without ``--review`` a small synthetic export is written.  Exit 0 when every check passes, 1 naming
the first failure, 2 on bad input.

    python -m tools.review_e2e --label-studio /path/to/venv/bin/label-studio [--review DIR] [--keep]
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import socket
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

from pipeline import catalog
from pipeline.runtime.errors import InputError
from pipeline.review.corrections import coco_decode, correction_masks, import_corrections, read_review
from pipeline.review.export import LS_RECORD_KEY, server_env, write_export
from pipeline.review.formats import LABEL, LS_FROM_NAME, LS_TO_NAME, ls_brush_rgba, ls_rle_encode_values
from pipeline.review.labelstudio import Client, check_served, upload_review

TOKEN = "geodistill-e2e-token-0123456789abcdef01234567"  # a throwaway server's legacy API token


def synthetic_export(workdir: Path, n: int = 4, size: tuple[int, int] = (48, 64)) -> Path:
    """A review export of ``n`` synthetic images under ``workdir`` (deterministic); returns its folder."""
    import cv2
    import pandas as pd

    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:size[0], :size[1]]
    root = workdir / "images"
    rows, masks = [], {}
    for i in range(n):
        cy, cx, ry, rx = rng.uniform(10, 38), rng.uniform(10, 54), rng.uniform(4, 14), rng.uniform(4, 20)
        m = ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 <= 1
        if i == 1:
            m &= ((yy - cy) / (ry / 3)) ** 2 + ((xx - cx) / (rx / 3)) ** 2 > 1   # a hole
        if i == 2:
            m[:, :3] = True                                                     # touches the edge
        if i == 3:
            m[:] = False                                                        # no vote: the person draws it
        iid, file = f"e2e/{i:02d}", f"e2e/{i:02d}.png"
        (root / "e2e").mkdir(parents=True, exist_ok=True)
        cv2.imwrite(str(root / file), rng.integers(0, 256, (*size, 3), dtype=np.uint8))
        masks[iid] = m
        rows.append({"image_id": iid, "file": file, "width": size[1], "height": size[0], "g": i / n, "h": 0.0})
    out = workdir / "review"
    write_export(out, pd.DataFrame(rows), masks.__getitem__, top=None, ranking="gate", ls_shape="brush",
                 coco_shape="rle", image_url=None, identity={"teacher": "review-e2e"}, image_root=root,
                 record={"label_dir": None, "input": str(root), "simulator": True})
    return out


def drawn_stroke(height: int, width: int) -> np.ndarray:
    """uint8 [H,W] alpha of an anti-aliased round-capped brush stroke across the image (soft edges)."""
    import cv2

    alpha = np.zeros((height, width), np.uint8)
    p0 = (int(width * 0.12), int(height * 0.8))
    p1 = (int(width * 0.85), int(height * 0.25))
    cv2.line(alpha, p0, p1, 255, max(3, min(height, width) // 10), cv2.LINE_AA)
    return alpha


def stroke_result(alpha: np.ndarray) -> dict:
    """The brush result Label Studio's editor submits for a stroke of layer alpha ``alpha``."""
    h, w = alpha.shape
    return {"id": "stroke", "type": "brushlabels", "from_name": LS_FROM_NAME, "to_name": LS_TO_NAME,
            "original_width": int(w), "original_height": int(h), "image_rotation": 0, "origin": "manual",
            "value": {"format": "rle", "rle": ls_rle_encode_values(ls_brush_rgba(alpha)), "brushlabels": [LABEL]}}


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_server(label_studio: str, layout: dict, workdir: Path) -> tuple[subprocess.Popen, Client]:
    """Start Label Studio serving ``layout``'s local files; (the process, a client) once it answers."""
    port = _free_port()
    env = {**os.environ, **server_env(layout), "LABEL_STUDIO_USERNAME": "e2e@example.com",
           "LABEL_STUDIO_PASSWORD": "e2e-password-1", "LABEL_STUDIO_USER_TOKEN": TOKEN,
           "LABEL_STUDIO_ENABLE_LEGACY_API_TOKEN": "true", "LABEL_STUDIO_DISABLE_SIGNUP_WITHOUT_LINK": "true"}
    with open(workdir / "label-studio.log", "w") as log:
        proc = subprocess.Popen([label_studio, "start", "--no-browser", "--port", str(port), "--data-dir",
                                 str(workdir / "data")], env=env, stdout=log, stderr=subprocess.STDOUT)
    client = Client(f"http://127.0.0.1:{port}", TOKEN)
    for _ in range(600):   # the first start migrates its database: minutes on a small host
        try:
            client.request("GET", "/api/projects")
            return proc, client
        except InputError:
            if proc.poll() is not None:
                raise RuntimeError(f"label-studio exited ({proc.returncode}); see {workdir / 'label-studio.log'}")
            time.sleep(1)
    proc.terminate()
    raise RuntimeError(f"label-studio did not answer in 10 min; see {workdir / 'label-studio.log'}")


def round_trip(client: Client, review_dir: Path, workdir: Path) -> list[str]:
    """Upload, check every image URL, annotate every task with its pre-annotation plus a drawn stroke, export
    and import; returns the failures."""
    rec = read_review(review_dir)
    res = upload_review(client, review_dir, "geodistill review-e2e")
    files = {im["image_id"]: Path(rec.get("input") or "") / im["file"] for im in rec["images"]}
    tasks = client.request("GET", f"/api/projects/{res['project']}/tasks?page_size=1000")
    tasks = tasks["tasks"] if isinstance(tasks, dict) else tasks
    want, strokes = {}, {}
    for task in tasks:
        iid = task["data"]["image_id"]
        check_served(client, task["data"]["image"], files[iid], rec[LS_RECORD_KEY])
        im = next(i for i in rec["images"] if i["image_id"] == iid)
        alpha = drawn_stroke(im["height"], im["width"])
        stroke = stroke_result(alpha)
        preds = client.request("GET", f"/api/tasks/{task['id']}").get("predictions") or []
        result = (preds[0]["result"] if preds else []) + [stroke]
        client.request("POST", f"/api/tasks/{task['id']}/annotations", {"result": result})
        want[iid] = coco_decode(im["voted_rle"]) | (alpha > 0)
        strokes[iid] = stroke["value"]["rle"]
    exported = client.request("GET", f"/api/projects/{res['project']}/export?exportType=JSON")
    bad = []
    for task in exported:
        got = [r["value"]["rle"] for a in task.get("annotations", []) for r in a["result"] if r.get("id") == "stroke"]
        if got != [strokes[task["data"]["image_id"]]]:
            bad.append(f"{task['data']['image_id']}: the exported stroke is not the submitted one")
    src = workdir / "export.json"
    src.write_text(json.dumps(exported))
    got = correction_masks(import_corrections(src, review_dir, catalog.path("corrections", workdir), fmt="labelstudio"))
    bad += [f"{i}: review import's mask differs from the vote + the drawn stroke" for i in want
            if i not in got or not np.array_equal(got[i], want[i])]
    return bad


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--label-studio", default=shutil.which("label-studio"), help="the label-studio executable")
    ap.add_argument("--review", type=Path, default=None, help="a review export folder (default: synthetic)")
    ap.add_argument("--keep", action="store_true", help="keep the work folder (server data, log, export)")
    args = ap.parse_args(argv)
    if not args.label_studio:
        print("review-e2e: no label-studio executable (pass --label-studio; `make review-e2e` installs one)",
              file=sys.stderr)
        return 2
    workdir = Path(tempfile.mkdtemp(prefix="review-e2e-"))
    proc = None
    try:
        review_dir = args.review if args.review is not None else synthetic_export(workdir)
        rec = read_review(review_dir)
        if not rec.get(LS_RECORD_KEY) or rec.get("ls_shape") != "brush":
            raise InputError(f"{review_dir}: review-e2e needs an export with Label Studio local-file URLs "
                             f"and brush pre-annotations (review export without --image-url and --ls-shape)")
        proc, client = start_server(args.label_studio, rec[LS_RECORD_KEY], workdir)
        version = client.request("GET", "/api/version").get("release", "?")
        bad = round_trip(client, review_dir, workdir)
    except InputError as e:
        print(f"review-e2e: {e}", file=sys.stderr)
        return 2
    finally:
        if proc is not None:
            proc.terminate()
            try:
                proc.wait(30)
            except subprocess.TimeoutExpired:
                proc.kill()
        if not args.keep:
            shutil.rmtree(workdir, ignore_errors=True)
    n = len(rec["images"])
    if bad:
        print(f"review-e2e: label-studio {version}: {len(bad)} of {n} failed (first: {bad[0]})", file=sys.stderr)
        return 1
    print(f"review-e2e: label-studio {version}: {n} tasks uploaded with their Local files storage, every image "
          f"served byte for byte, a drawn anti-aliased stroke on each came back through review import bit for bit")
    return 0


if __name__ == "__main__":
    sys.exit(main())
