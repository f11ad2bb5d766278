"""The review loop against Label Studio and CVAT without a server: the requests ``review upload`` sends
(project, Local files storage connection, tasks, the image fetch) through a fake HTTP layer, the task
URLs checked against Label Studio's own serving rule, a drawn anti-aliased brush correction read back by
``review import``, and a CVAT export with an image nobody drew on (``make review-e2e`` does the same with
a real server, opt-in)."""

from __future__ import annotations

import io
import json
import os
import urllib.error
import urllib.parse
from pathlib import Path

import numpy as np
import pytest

from pipeline.runtime.errors import InputError
from pipeline.review.corrections import coco_decode, correction_masks, import_corrections, read_review
from tools.review_e2e import drawn_stroke, stroke_result, synthetic_export
from pipeline.review.formats import ls_rle_decode
from pipeline.review.export import LOCAL_FILES_URL, local_files_layout, local_files_url
from pipeline.review.labelstudio import STORAGE_API, Client, upload_review
from tests.builders.teacher import cli

pytestmark = pytest.mark.filterwarnings("ignore:__array__ implementation:DeprecationWarning")


class FakeServer:
    """urllib's ``urlopen`` stand-in: records each request, answers like Label Studio 1.23's API, and
    serves ``/data/local-files/?d=`` by Label Studio's rule (views.localfiles_data): the file under the
    document root, only inside a storage path created before."""

    def __init__(self, document_root: str):
        self.root, self.storages, self.calls = document_root, [], []

    def __call__(self, req, timeout=None):
        url = urllib.parse.urlsplit(req.full_url)
        body = json.loads(req.data) if req.data else None
        self.calls.append((req.get_method(), url.path, body, dict(req.header_items())))
        if url.path == "/api/token/refresh":
            return io.BytesIO(json.dumps({"access": "ACCESS"}).encode())
        if url.path == "/api/projects":
            return io.BytesIO(b'{"id": 7}')
        if url.path == STORAGE_API:
            self.storages.append(body["path"])
            return io.BytesIO(b'{"id": 3}')
        if url.path.endswith("/import"):
            return io.BytesIO(json.dumps({"task_count": len(body)}).encode())
        if url.path == "/data/local-files/":
            full = os.path.normpath(os.path.join(self.root, urllib.parse.parse_qs(url.query)["d"][0].lstrip("/")))
            folder = os.path.dirname(full)
            if any(folder == s or folder.startswith(s + os.sep) for s in self.storages) and os.path.exists(full):
                return io.BytesIO(Path(full).read_bytes())
        raise urllib.error.HTTPError(req.full_url, 404, "Not Found", {}, io.BytesIO(b"not found"))


@pytest.fixture(scope="module")
def review(tmp_path_factory) -> Path:
    return synthetic_export(tmp_path_factory.mktemp("ls"))


def test_upload_creates_the_local_files_storage_that_serves_the_task_urls(review):
    rec = read_review(review)
    layout = rec["label_studio"]
    root, storage = Path(layout["document_root"]), Path(layout["storage_path"])
    assert root in storage.parents                       # Label Studio refuses a storage path = the root
    tasks = json.loads((review / "labelstudio" / "tasks.json").read_text())
    for task, im in zip(tasks, rec["images"]):
        url = task["data"]["image"]
        assert url.startswith(LOCAL_FILES_URL)
        served = root / urllib.parse.parse_qs(urllib.parse.urlsplit(url).query)["d"][0]
        assert served == storage / im["file"] and served.is_file()

    server = FakeServer(layout["document_root"])
    res = upload_review(Client("http://ls:8080/", "legacy-token", opener=server), review)
    assert res == {"project": 7, "storage": 3, "tasks": len(tasks), "served": True}
    (m1, p1, b1, _), (m2, p2, b2, _), (m3, p3, b3, _), (m4, p4, _, h4) = server.calls
    assert (m1, p1) == ("POST", "/api/projects") and "<BrushLabels" in b1["label_config"]
    assert (m2, p2) == ("POST", STORAGE_API)
    assert b2["project"] == 7 and b2["path"] == str(storage) and b2["use_blob_urls"] is True
    assert (m3, p3, b3) == ("POST", "/api/projects/7/import", tasks)
    assert (m4, p4) == ("GET", "/data/local-files/") and h4["Authorization"] == "Token legacy-token"


def test_upload_says_how_to_start_label_studio_when_the_image_is_not_served(review):
    layout = read_review(review)["label_studio"]
    server = FakeServer("/elsewhere")                     # started with another document root
    with pytest.raises(InputError) as e:
        upload_review(Client("http://ls:8080", "t", opener=server), review)
    msg = str(e.value)
    assert "\n" not in msg and "HTTP 404" in msg and f"LABEL_STUDIO_LOCAL_FILES_DOCUMENT_ROOT={layout['document_root']}" in msg
    assert "LABEL_STUDIO_LOCAL_FILES_SERVING_ENABLED=true" in msg


def test_personal_access_token_is_exchanged_for_an_access_token(tmp_path):
    server = FakeServer(str(tmp_path))
    client = Client("http://ls:8080", "aaa.bbb.ccc", opener=server)
    client.request("POST", "/api/projects", {"title": "x"})
    (m0, p0, b0, h0), (_, _, _, h1) = server.calls
    assert (m0, p0, b0) == ("POST", "/api/token/refresh", {"refresh": "aaa.bbb.ccc"}) and "Authorization" not in h0
    assert h1["Authorization"] == "Bearer ACCESS"


def test_local_file_urls_are_percent_encoded_and_need_a_folder_above(tmp_path):
    images = tmp_path / "my images"
    layout = local_files_layout([images / "a+b #1.png"], images)
    url = local_files_url(images / "a+b #1.png", layout)
    assert url == LOCAL_FILES_URL + "my%20images/a%2Bb%20%231.png"
    assert urllib.parse.parse_qs(urllib.parse.urlsplit(url).query)["d"] == ["my images/a+b #1.png"]
    assert local_files_layout([tmp_path / "x" / "1.png", tmp_path / "y" / "2.png"])["storage_path"] == str(tmp_path)
    # a DAG run's manifest names its images from the project root: the record stays relative
    assert local_files_layout([Path("art/syn/images/1.png")]) == {"document_root": "art/syn",
                                                                   "storage_path": "art/syn/images"}
    with pytest.raises(InputError, match="file-system root"):
        local_files_layout([Path("/a.png")])


def test_upload_cli_one_line_when_no_server(review):
    res = cli("review", "upload", review, "--url", "http://127.0.0.1:9", "--token", "t")
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1 and "Label Studio at" in res.output


def test_a_drawn_anti_aliased_brush_correction_comes_back_through_review_import(review, tmp_path):
    """What make review-e2e submits, as Label Studio's JSON export returns it: the pre-annotation plus a
    stroke with soft edges (alpha 1..254), imported as the vote united with alpha > 0."""
    rec = read_review(review)
    tasks = json.loads((review / "labelstudio" / "tasks.json").read_text())
    want = {}
    for k, task in enumerate(tasks):
        im = next(i for i in rec["images"] if i["image_id"] == task["data"]["image_id"])
        alpha = drawn_stroke(im["height"], im["width"])
        assert ((alpha > 0) & (alpha < 255)).any()       # anti-aliased: soft edge pixels
        stroke = stroke_result(alpha)
        assert (ls_rle_decode(stroke["value"]["rle"], *alpha.shape) == (alpha > 0)).all()
        task["id"] = k + 1
        task["annotations"] = [{"was_cancelled": False,
                                "result": (task["predictions"][0]["result"] if task["predictions"] else []) + [stroke]}]
        want[im["image_id"]] = coco_decode(im["voted_rle"]) | (alpha > 0)
    src = tmp_path / "ls_export.json"
    src.write_text(json.dumps(tasks))
    got = correction_masks(import_corrections(src, review, tmp_path / "c.parquet", fmt="labelstudio"))
    assert set(got) == set(want) and all(np.array_equal(got[i], want[i]) for i in want)


def test_cvat_export_with_an_image_nobody_drew_on_imports_the_others(review, tmp_path):
    rec = read_review(review)
    coco = json.loads((review / "cvat" / "instances_default.json").read_text())
    drawn = {a["image_id"] for a in coco["annotations"]}
    empty = [im for im in coco["images"] if im["id"] not in drawn]
    assert len(empty) == 1                               # the export's empty vote: CVAT lists it, undrawn
    coco["images"].append({"id": 99, "file_name": "not/exported.png", "width": 5, "height": 5})   # whole-folder task
    src = tmp_path / "instances_default.json"
    src.write_text(json.dumps(coco))
    res = cli("review", "import", src, "--review", review, "--out", tmp_path / "c.parquet")
    assert res.exit_code == 0, res.output
    got = correction_masks(import_corrections(src, review, tmp_path / "c.parquet", fmt="cvat", overwrite=True))
    by_file = {im["file"]: im for im in rec["images"]}
    assert by_file[empty[0]["file_name"]]["image_id"] not in got
    assert len(got) == len(rec["images"]) - 1
    assert all(np.array_equal(got[i["image_id"]], coco_decode(i["voted_rle"])) for i in rec["images"] if i["image_id"] in got)
    assert f"of the export's {len(rec['images'])} images" in res.output and "other 1 not corrected" in res.output

    coco["annotations"].append({"id": 500, "image_id": 99, "category_id": 1, "iscrowd": 0,
                                "segmentation": [[0, 0, 3, 0, 3, 3]]})   # drawn on an image the export lacks
    src.write_text(json.dumps(coco))
    res = cli("review", "import", src, "--review", review, "--out", tmp_path / "d.parquet")
    assert res.exit_code == 2 and len(res.output.strip().splitlines()) == 1 and "not/exported.png" in res.output
