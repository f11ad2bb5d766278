"""The opt-in end-to-end check of the Label Studio round trip (``make review-e2e``; never in CI, never
needed at run time): start a real Label Studio server, import the tasks through its HTTP API, accept
every pre-annotation as the annotation, export the project as JSON and check that each mask comes
back bit for bit.

    python -m pipeline.review.e2e --label-studio /path/to/venv/bin/label-studio [--review DIR]

``--review DIR``: a finished ``geodistill review export`` folder; its ``labelstudio/tasks.json`` and
``label_config.xml`` are imported, and the export is read back by ``review import``'s own reader
(:mod:`pipeline.review.corrections`), each mask compared with the voted mask recorded in
``review.json``.  Without it, a handful of synthetic masks (ellipses, a hole, an edge-touching one) go
through as brush pre-annotations and come back through :func:`pipeline.review.formats.ls_rle_decode`.
Images need not be served: Label Studio stores and exports the results without loading them.

Exit 0 when every mask matches; 1 with the first mismatch named otherwise.
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
import urllib.request
from pathlib import Path

import numpy as np

from pipeline import catalog
from pipeline.review.corrections import coco_decode, correction_masks, import_corrections, read_review
from pipeline.review.export import MODEL_VERSION
from pipeline.review.formats import ls_label_config, ls_results, ls_rle_decode

TOKEN = "geodistill-e2e-token-0123456789abcdef01234567"  # a throwaway server's legacy API token


def synthetic_tasks(n: int = 4, size: tuple[int, int] = (48, 64)) -> tuple[list[dict], dict[str, np.ndarray]]:
    """``n`` brush pre-annotated tasks and their masks by image id (deterministic)."""
    rng = np.random.default_rng(0)
    yy, xx = np.mgrid[:size[0], :size[1]]
    tasks, masks = [], {}
    for i in range(n):
        cy, cx, ry, rx = rng.uniform(10, 38), rng.uniform(10, 54), rng.uniform(4, 14), rng.uniform(4, 20)
        m = ((yy - cy) / ry) ** 2 + ((xx - cx) / rx) ** 2 <= 1
        if i == 1:
            m &= ((yy - cy) / (ry / 3)) ** 2 + ((xx - cx) / (rx / 3)) ** 2 > 1   # a hole
        if i == 2:
            m[:, :3] = True                                                     # touches the edge
        iid = f"e2e/{i:02d}"
        masks[iid] = m
        tasks.append({"data": {"image": f"/data/local-files/?d={iid}.png", "image_id": iid},
                      "predictions": [{"model_version": MODEL_VERSION, "result": ls_results(m)}]})
    return tasks, masks


def _api(base: str, path: str, data=None, method: str | None = None):
    body = None if data is None else json.dumps(data).encode()
    req = urllib.request.Request(base + path, data=body, method=method or ("POST" if body else "GET"),
                                 headers={"Authorization": f"Token {TOKEN}", "Content-Type": "application/json"})
    with urllib.request.urlopen(req, timeout=120) as r:
        return json.loads(r.read() or b"null")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def round_trip(label_studio: str, tasks: list[dict], config: str, workdir: Path) -> list[dict]:
    """Start the server, import ``tasks`` into a project with ``config``, turn each task's prediction
    into its annotation, and return the project's JSON export (the server is stopped afterwards)."""
    port = _free_port()
    env = {**os.environ, "LABEL_STUDIO_USERNAME": "e2e@example.com", "LABEL_STUDIO_PASSWORD": "e2e-password-1",
           "LABEL_STUDIO_USER_TOKEN": TOKEN, "LABEL_STUDIO_ENABLE_LEGACY_API_TOKEN": "true",
           "LABEL_STUDIO_DISABLE_SIGNUP_WITHOUT_LINK": "true"}
    log = open(workdir / "label-studio.log", "w")
    proc = subprocess.Popen([label_studio, "start", "--no-browser", "--port", str(port), "--data-dir",
                             str(workdir / "data")], env=env, stdout=log, stderr=subprocess.STDOUT)
    base = f"http://127.0.0.1:{port}"
    try:
        for _ in range(300):   # first start migrates its database: up to a few minutes
            try:
                _api(base, "/api/projects")
                break
            except OSError:
                if proc.poll() is not None:
                    raise RuntimeError(f"label-studio exited ({proc.returncode}); see {workdir / 'label-studio.log'}")
                time.sleep(1)
        project = _api(base, "/api/projects", {"title": "geodistill e2e", "label_config": config})
        _api(base, f"/api/projects/{project['id']}/import", tasks)
        for task in _api(base, f"/api/projects/{project['id']}/tasks?page_size=1000"):
            detail = _api(base, f"/api/tasks/{task['id']}")
            preds = detail.get("predictions") or []
            if preds:
                _api(base, f"/api/tasks/{task['id']}/annotations", {"result": preds[0]["result"]})
        return _api(base, f"/api/projects/{project['id']}/export?exportType=JSON")
    finally:
        proc.terminate()
        try:
            proc.wait(30)
        except subprocess.TimeoutExpired:
            proc.kill()
        log.close()


def check_synthetic(exported: list[dict], masks: dict[str, np.ndarray]) -> list[str]:
    """The image ids whose exported brush mask differs from the imported one (or is missing)."""
    bad = []
    for task in exported:
        iid = task["data"]["image_id"]
        want = masks[iid]
        res = [r for a in task.get("annotations", []) for r in a.get("result", [])]
        got = np.zeros_like(want)
        for r in res:
            got |= ls_rle_decode(r["value"]["rle"], *want.shape)
        if not res or not np.array_equal(got, want):
            bad.append(iid)
    return bad + sorted(set(masks) - {t["data"]["image_id"] for t in exported})


def check_review(exported: list[dict], review_dir: Path, workdir: Path) -> list[str]:
    """Read the export back with ``review import`` and compare each mask with the recorded vote."""
    src = workdir / "export.json"
    src.write_text(json.dumps(exported))
    art = import_corrections(src, review_dir, catalog.path("corrections", workdir), fmt="labelstudio")
    got = correction_masks(art)
    voted = {im["image_id"]: coco_decode(im["voted_rle"]) for im in read_review(review_dir)["images"]
             if im.get("voted_rle") and coco_decode(im["voted_rle"]).any()}
    return sorted(i for i in voted if i not in got or not np.array_equal(got[i], voted[i]))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--label-studio", default=shutil.which("label-studio"), help="the label-studio executable")
    ap.add_argument("--review", type=Path, default=None, help="a review export folder (default: synthetic masks)")
    ap.add_argument("--keep", action="store_true", help="keep the server's data folder")
    args = ap.parse_args(argv)
    if not args.label_studio:
        print("review-e2e: no label-studio executable (pass --label-studio; `make review-e2e` installs one)",
              file=sys.stderr)
        return 2
    workdir = Path(tempfile.mkdtemp(prefix="review-e2e-"))
    if args.review is not None:
        ls = args.review / "labelstudio"
        tasks, config = json.loads((ls / "tasks.json").read_text()), (ls / "label_config.xml").read_text()
    else:
        (tasks, masks), config = synthetic_tasks(), ls_label_config("brush")
    exported = round_trip(args.label_studio, tasks, config, workdir)
    bad = check_review(exported, args.review, workdir) if args.review is not None else check_synthetic(exported, masks)
    n = len(exported)
    if not args.keep:
        shutil.rmtree(workdir, ignore_errors=True)
    if bad:
        print(f"review-e2e: {len(bad)} of {n} masks did not come back bit for bit (first: {bad[0]})", file=sys.stderr)
        return 1
    print(f"review-e2e: {n} tasks through a real Label Studio server and back, every mask bit for bit")
    return 0


if __name__ == "__main__":
    sys.exit(main())
