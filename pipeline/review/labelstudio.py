"""Label Studio through its HTTP API (``geodistill review upload``): a project for a review export, the
Local files storage that serves its images (without it the local-files URLs give 404s:
:func:`pipeline.review.export.local_files_layout`), and its tasks.
"""

from __future__ import annotations

import json
import urllib.error
import urllib.request
from pathlib import Path
from typing import Callable

from pipeline.runtime.errors import InputError
from pipeline.review.corrections import read_review
from pipeline.review.export import LS_CONFIG, LS_RECORD_KEY, LS_TASKS, OUTPUTS, server_env

__all__ = ["Client", "upload_review", "check_served"]

STORAGE_API = "/api/storages/localfiles"


class Client:
    """A Label Studio server at ``url`` with ``token``: a legacy API token or a personal access token (a JWT)."""

    def __init__(self, url: str, token: str, opener: Callable = urllib.request.urlopen, timeout: float = 120):
        self.url, self.opener, self.timeout = url.rstrip("/"), opener, timeout
        self.auth = f"Token {token}"
        if token.count(".") == 2:   # a PAT is a JWT refresh token; the API wants its access token
            self.auth = f"Bearer {self.request('POST', '/api/token/refresh', {'refresh': token}, auth=False)['access']}"

    def request(self, method: str, path: str, data=None, *, raw: bool = False, auth: bool = True):
        """``method path`` with a JSON body; the JSON answer (``raw``: its bytes); one-line InputError on failure."""
        headers = {"Content-Type": "application/json"}
        if auth:
            headers["Authorization"] = self.auth
        body = None if data is None else json.dumps(data).encode()
        req = urllib.request.Request(self.url + path, data=body, method=method, headers=headers)
        try:
            with self.opener(req, timeout=self.timeout) as r:
                out = r.read()
        except urllib.error.HTTPError as e:
            detail = " ".join(e.read().decode(errors="replace").split())[:400]
            raise InputError(f"Label Studio at {self.url}: {method} {path}: HTTP {e.code} {detail}") from None
        except OSError as e:
            raise InputError(f"Label Studio at {self.url}: {method} {path}: {e}") from None
        return out if raw else json.loads(out or b"null")


def upload(client: Client, tasks: list[dict], label_config: str, layout: dict | None, title: str,
           first_image: Path | None = None) -> dict:
    """Create a project, its Local files storage for ``layout`` (None: served elsewhere) and ``tasks``; check
    the first task's URL serves ``first_image``.  -> ``{"project", "storage", "tasks", "served"}``.
    """
    project = client.request("POST", "/api/projects", {"title": title, "label_config": label_config})
    storage = None
    if layout is not None:   # a Local files storage whose path covers the images
        storage = client.request("POST", STORAGE_API, {
            "project": int(project["id"]), "title": "geodistill review images",
            "path": str(Path(layout["storage_path"]).resolve()), "regex_filter": "", "use_blob_urls": True,
            "recursive_scan": True})["id"]
    client.request("POST", f"/api/projects/{project['id']}/import", tasks)
    served = bool(first_image is not None and tasks and tasks[0]["data"]["image"].startswith("/"))  # on this server
    if served:
        check_served(client, tasks[0]["data"]["image"], Path(first_image), layout)
    return {"project": project["id"], "storage": storage, "tasks": len(tasks), "served": served}


def upload_review(client: Client, review_dir: str | Path, title: str | None = None) -> dict:
    """:func:`upload` of a ``review export`` folder (``title`` default ``geodistill review <export id>``)."""
    rec = read_review(review_dir)
    folder = Path(review_dir) / OUTPUTS["labelstudio"]
    tasks = json.loads((folder / LS_TASKS).read_text())
    layout = rec.get(LS_RECORD_KEY)
    # a label export's files are relative to its input folder; the DAG stage's are the manifest's paths
    first = Path(rec.get("input") or "") / rec["images"][0]["file"] if layout and rec["images"] else None
    return upload(client, tasks, (folder / LS_CONFIG).read_text(), layout,
                  title or f"geodistill review {rec['export_id']}", first)


def check_served(client: Client, url: str, image: Path, layout: dict | None) -> None:
    """InputError unless the task URL ``url`` returns the bytes of ``image``."""
    try:
        got = client.request("GET", url, raw=True)
    except InputError as e:
        hint = (f" (start Label Studio with {' '.join(f'{k}={v}' for k, v in server_env(layout).items())})"
                if layout is not None else "")
        raise InputError(f"{image}: Label Studio does not serve it: {e}{hint}") from None
    if got != image.read_bytes():
        raise InputError(f"{image}: Label Studio's {url} returns other bytes than the file ({len(got)} bytes)")
