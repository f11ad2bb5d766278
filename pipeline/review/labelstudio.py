"""Label Studio through its HTTP API (``geodistill review upload``).

It makes a project for a review export, the Local files storage that serves its images (without it the
local-files URLs give 404s: :func:`pipeline.review.export.local_files_layout`), and its tasks.
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
    """A Label Studio server at ``url`` with ``token``: a legacy API token or a personal access token (a JWT).

    A personal access token is exchanged for its access token once, on construction.

    Parameters
    ----------
    url : str
        The server's base URL (a trailing ``/`` is dropped).
    token : str
        A legacy API token, or a personal access token (a JWT refresh token: three ``.``-separated parts).
    opener : callable
        Opens a :class:`urllib.request.Request` (``urllib.request.urlopen``; tests pass a fake server).
    timeout : float
        Seconds to wait for each answer.
    """

    def __init__(self, url: str, token: str, opener: Callable = urllib.request.urlopen, timeout: float = 120):
        self.url, self.opener, self.timeout = url.rstrip("/"), opener, timeout
        self.auth = f"Token {token}"
        if token.count(".") == 2:   # a PAT is a JWT refresh token; the API wants its access token
            self.auth = f"Bearer {self.request('POST', '/api/token/refresh', {'refresh': token}, auth=False)['access']}"

    def request(self, method: str, path: str, data=None, *, raw: bool = False, auth: bool = True):
        """Send ``method path`` with a JSON body and read the answer.

        Parameters
        ----------
        method : str
            The HTTP method (``GET``, ``POST``).
        path : str
            The path from the server's base URL (``/api/projects``).
        data : object, optional
            The JSON body; None sends none.
        raw : bool
            Return the answer's bytes instead of its parsed JSON.
        auth : bool
            Send the ``Authorization`` header (off for the token exchange itself).

        Returns
        -------
        object
            The parsed JSON answer (None for an empty one), or its bytes with ``raw``.

        Raises
        ------
        pipeline.runtime.errors.InputError
            One line naming the server, method and path, on an HTTP error (with the start of its body) or when
            the server cannot be reached.
        """
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
    """Create a project, its Local files storage for ``layout`` (None: served elsewhere) and ``tasks``.

    When the tasks' URLs are on this server, the first one is checked to serve ``first_image``
    (:func:`check_served`).  Returns ``{"project", "storage", "tasks", "served"}``.
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
    """Upload a ``review export`` folder to Label Studio: a project, its image storage and its tasks.

    Parameters
    ----------
    client : Client
        The server.
    review_dir : str or Path
        The ``review export`` folder (its record, Label Studio tasks and labelling config).
    title : str, optional
        The project's title; None: ``geodistill review <export id>``.

    Returns
    -------
    dict
        ``project`` (its id), ``storage`` (the Local files storage's id, None when the images are served
        elsewhere), ``tasks`` (how many) and ``served`` (whether the first image was checked to be served).
    """
    rec = read_review(review_dir)
    folder = Path(review_dir) / OUTPUTS["labelstudio"]
    tasks = json.loads((folder / LS_TASKS).read_text())
    layout = rec.get(LS_RECORD_KEY)
    # a label export's files are relative to its input folder; the DAG stage's are the manifest's paths
    first = Path(rec.get("input") or "") / rec["images"][0]["file"] if layout and rec["images"] else None
    return upload(client, tasks, (folder / LS_CONFIG).read_text(), layout,
                  title or f"geodistill review {rec['export_id']}", first)


def check_served(client: Client, url: str, image: Path, layout: dict | None) -> None:
    """Check that the task URL ``url`` returns the bytes of ``image``.

    Parameters
    ----------
    client : Client
        The server.
    url : str
        The task's image URL (a path on the server).
    image : Path
        The image file it should serve.
    layout : dict or None
        The export's Local files layout (:func:`pipeline.review.export.local_files_layout`), for the hint
        naming the environment Label Studio must start with; None: no hint.

    Raises
    ------
    pipeline.runtime.errors.InputError
        Naming ``image`` when the server does not serve it, or serves other bytes.
    """
    try:
        got = client.request("GET", url, raw=True)
    except InputError as e:
        hint = (f" (start Label Studio with {' '.join(f'{k}={v}' for k, v in server_env(layout).items())})"
                if layout is not None else "")
        raise InputError(f"{image}: Label Studio does not serve it: {e}{hint}") from None
    if got != image.read_bytes():
        raise InputError(f"{image}: Label Studio's {url} returns other bytes than the file ({len(got)} bytes)")
