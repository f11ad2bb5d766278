"""Label Studio through its HTTP API: a project for a review export, the Local files storage
connection that serves its images, and its tasks (``geodistill review upload``; ``make review-e2e``).

How Label Studio serves a task's ``/data/local-files/?d=PATH`` (checked in label-studio 1.23.2,
``io_storages/localfiles/views.py`` and ``models.py``): only with ``LABEL_STUDIO_LOCAL_FILES_SERVING_ENABLED
=true``, with PATH relative to ``LABEL_STUDIO_LOCAL_FILES_DOCUMENT_ROOT``, and only when a Local files
import storage of a project the user can see has a ``path`` that contains the file's folder; that path
must be a strict sub-folder of the document root.  So the two environment variables alone give 404s.

:func:`pipeline.review.export.local_files_layout` is that layout for a set of images: the storage path
is the folder holding them (a ``label`` run's input folder), the document root its parent, and each
URL the image's path from the document root.  ``review export`` writes its tasks so and records both
folders in ``review.json`` (``label_studio``); :func:`upload` creates the project, the storage connection
(:func:`storage_request`; never synced: the tasks are imported as exported, with their pre-annotations)
and the tasks, then fetches the first image to prove it is served.
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

STORAGE_API = "/api/storages/localfiles"


def storage_request(project_id: int, layout: dict, title: str = "geodistill review images") -> dict:
    """The body of ``POST /api/storages/localfiles``: a Local files import storage of the project whose
    path covers the images (``use_blob_urls``: files are images, referenced by URL, not JSON tasks)."""
    return {"project": int(project_id), "title": title, "path": str(Path(layout["storage_path"]).resolve()),
            "regex_filter": "", "use_blob_urls": True, "recursive_scan": True}


class Client:
    """A Label Studio server at ``url`` reached with ``token`` -- a legacy API token, or a personal access
    token (a JWT: exchanged once for an access token at ``/api/token/refresh``).  ``opener``: urllib's
    ``urlopen`` (tests pass a fake)."""

    def __init__(self, url: str, token: str, opener: Callable = urllib.request.urlopen, timeout: float = 120):
        self.url, self.opener, self.timeout = url.rstrip("/"), opener, timeout
        self.auth = f"Token {token}"
        if token.count(".") == 2:   # a PAT is a JWT refresh token; the API wants its access token
            self.auth = f"Bearer {self.request('POST', '/api/token/refresh', {'refresh': token}, auth=False)['access']}"

    def request(self, method: str, path: str, data=None, *, raw: bool = False, auth: bool = True):
        """``method path`` with a JSON body ``data``; the JSON answer (``raw``: its bytes).  InputError
        with the server's answer in one line on an HTTP error or no connection."""
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
    """Create a project (``title``, ``label_config``), its Local files storage for ``layout`` (None: the
    tasks' URLs are served elsewhere) and ``tasks``; with ``first_image`` (the file of the first task)
    check its URL returns that file's bytes.  Returns ``{"project", "storage", "tasks", "served"}``."""
    project = client.request("POST", "/api/projects", {"title": title, "label_config": label_config})
    storage = None
    if layout is not None:
        storage = client.request("POST", STORAGE_API, storage_request(project["id"], layout))["id"]
    client.request("POST", f"/api/projects/{project['id']}/import", tasks)
    served = bool(first_image is not None and tasks and tasks[0]["data"]["image"].startswith("/"))  # on this server
    if served:
        check_served(client, tasks[0]["data"]["image"], Path(first_image), layout)
    return {"project": project["id"], "storage": storage, "tasks": len(tasks), "served": served}


def upload_review(client: Client, review_dir: str | Path, title: str | None = None) -> dict:
    """:func:`upload` of a ``review export`` folder: its tasks and interface, the storage its record
    names, the first exported image checked; ``title`` default ``geodistill review <export id>``."""
    rec = read_review(review_dir)
    folder = Path(review_dir) / OUTPUTS["labelstudio"]
    tasks = json.loads((folder / LS_TASKS).read_text())
    layout = rec.get(LS_RECORD_KEY)
    # a label export's files are relative to its input folder; the DAG stage's are the manifest's paths
    first = Path(rec.get("input") or "") / rec["images"][0]["file"] if layout and rec["images"] else None
    return upload(client, tasks, (folder / LS_CONFIG).read_text(), layout,
                  title or f"geodistill review {rec['export_id']}", first)


def check_served(client: Client, url: str, image: Path, layout: dict | None) -> None:
    """InputError unless ``url`` (a task's image URL) returns the bytes of file ``image``."""
    try:
        got = client.request("GET", url, raw=True)
    except InputError as e:
        hint = (f" (start Label Studio with {' '.join(f'{k}={v}' for k, v in server_env(layout).items())})"
                if layout is not None else "")
        raise InputError(f"{image}: Label Studio does not serve it: {e}{hint}") from None
    if got != image.read_bytes():
        raise InputError(f"{image}: Label Studio's {url} returns other bytes than the file ({len(got)} bytes)")
