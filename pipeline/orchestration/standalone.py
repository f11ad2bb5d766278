"""``geodistill distill``: a folder of images in, a trained student, deploy bundle and report out -- by
running THE SAME DAG in a self-contained DVC project generated in the output folder.

Design (decision; the issue asks for "the same DAG ... reproducible and resumable"):

* ``OUT`` becomes a DVC project of its own (``dvc init --no-scm``, analytics off) holding

  - ``params.yaml``: the ``distill`` profile (:mod:`pipeline.profiles`: paper sizes, Plain Student
    then GeoDistill-Refine for seed 42) + the command's ``--params``/``--set`` + what points the data
    at the folder: ``data.source=folder``, ``data.root=INPUT``, ``data.protocol=folder_protocol.yaml``
    and the teacher (``--checkpoint`` -> backend sam3, or ``--backend imported --imported-dir``);
  - ``folder_protocol.yaml``: the ``folder`` adapter's protocol with ``images_dir`` = INPUT (read
    recursively, as label and segment read it) and ``masks_dir`` = ``--val-masks`` (absolute) or null;
  - ``dvc.yaml``: rendered by :func:`pipeline.orchestration.dag.render_dvc_yaml` from the catalogue, exactly as the
    repository's, except that code deps are the absolute paths of the installed code files (a code
    change reruns exactly the stages that import it) and the ``prepare`` stage depends on INPUT, the
    mask folder and the protocol file instead of ``data_manifests/`` (adding an image reruns it);
  - ``distill.json``: what the project was made from (input, masks, teacher, version) and the record
    of what distill writes there (:mod:`pipeline.artifacts.ownership`), written first: a rerun into the same
    folder resumes; a user's file where a project file goes (say, their own params.yaml) is refused
    before anything is written, ``overwrite`` or not, and a user's folder in the way (``artifacts/``)
    unless ``overwrite`` (``--overwrite``); files of the user's stay;
  - ``.cache/`` (decode cache, teacher cache, per-epoch training state; DVC-ignored): why a rerun, or a
    run killed half-way, resumes -- DVC skips finished stages, the teacher stage computes only the
    missing answers, a training stage continues from its last epoch.

* then ``python -m dvc repro`` runs in ``OUT`` with this interpreter's folder first on PATH (the
  stage commands are ``python -m stages.<name>``).  ``--device cpu`` hides CUDA from the stages
  (``CUDA_VISIBLE_DEVICES=""``); the default ``auto`` lets each stage use a GPU when there is one.
  Later, ``cd OUT && dvc repro`` works the same way: edit a value in params.yaml, run ``dvc repro``,
  and exactly the stages that read it rerun.  When a stage fails, its own one-line message is
  the one distill prints (DVC's "failed to reproduce" line is left out, :func:`run_project`), and
  DVC's closing "Use `dvc push` ..." is left out too (a distill project has no remote).

* git: where ``git`` is installed, a new project is a git repository of its own (:func:`init_git`:
  ``git init``, a ``.gitignore`` for the caches, ``dvc init`` with git, ``core.autostage`` on so DVC
  stages what it changes instead of printing ``git add`` hints, and one commit of the project files by
  "geodistill distill"), so ``dvc exp run -S key=value`` and ``dvc exp show`` work there.  Without
  git (or in a project made before) it is ``--no-scm``: ``dvc repro`` only, ``dvc exp`` needs git.

Validation masks (``--val-masks DIR``, named like the images): the ``folder`` protocol puts the images
that have a mask into validation and test (seeded halves, ``val_fraction`` 0.5) and trains on the
rest; validation masks select checkpoints and calibrate tau, test masks score the report.  Without
them: no image is held out, Stage II keeps its last epoch (``train.stage2_select`` is ``last``
anyway; Stage I selects the last epoch when there is no validation mask), tau is the fixed
``calibrate.fixed_tau`` = 0.5, and the report says that no masks were available.

The teacher: SAM 3 needs ``--checkpoint`` (a local ``save_pretrained`` folder); ``--backend imported``
reads masks made elsewhere.  ``--labels LABEL_DIR`` (``labels=``) takes the teacher and everything
else that made a ``label`` folder's pseudo-labels (resolution, vote, gate) from its label.json, after
checking the folder against the checksums recorded there, and points ``teacher.cache_dir`` at label's
teacher cache: the teacher stage finds every answer cached and computes none
(:func:`pipeline.api.params_from_labels`).  A ``label`` run and a ``distill`` run of the same images
share the answers this way only; the project's own ``.cache/teacher`` is used otherwise.  The simulated teacher cannot label a folder of your images for training:
it is a SIMULATOR that reads ground-truth masks of every training image, which a folder has not
(the ``folder`` protocol never gives a training image a mask) -- refused with one line.
"""

from __future__ import annotations

import json
import logging
import os
import re
import shutil
import subprocess
import sys
import threading
from pathlib import Path
from typing import Mapping
import yaml

from pipeline import __version__, catalog
from pipeline.artifacts.atomic import write_text_if_changed
from pipeline.training.budget import with_time_budget
from pipeline.runtime.codeversion import ROOT
from pipeline.orchestration.dag import live_plots, render_dvc_yaml, render_params_yaml
from pipeline.runtime.device import resolve_device
from pipeline.report.dvc_results import path_component
from pipeline.datasets.scan import scan_inputs
from pipeline.runtime.errors import BACKEND, CHECKPOINT, INPUT, OUT, VAL_MASKS, InputError, Option, literal
from pipeline.deploy.export import bundle_files
from pipeline.labeling.run import find_images
from pipeline.methods import PROPOSED, STAGE_ONE, method_label
from pipeline.report.offline_plots import template_path, template_text
from pipeline.artifacts.ownership import check_outputs, record_fields, refuse_foreign_files
from pipeline.params import deep_merge, read_yaml_mapping
from pipeline.runtime.progress import QUIET_ENV, bars_quiet

log = logging.getLogger(__name__)

PROFILE = "distill"
PARAMS_FILE, DVC_FILE, PROTOCOL_FILE, RECORD_FILE = catalog.output_names("project").values()
#: stages left out of a project without any mask: nothing to score (calibrate stays: it writes the fixed tau)
NO_MASK_STAGES = ("evaluate", "analyze_teacher")
#: the stage ``--no-benchmark`` leaves out (the report then says the efficiency table was not made)
BENCHMARK_STAGE = "benchmark"
DVCIGNORE = "/.cache/\n__pycache__/\n*.pyc\n"
#: what distill writes in --out (its record lists them; pipeline.artifacts.ownership): the project files, DVC's
#: folder and lock, the caches and the DAG's outputs (artifacts/, reports/)
PROJECT_OUTPUTS = (PARAMS_FILE, DVC_FILE, "dvc.lock", PROTOCOL_FILE, ".dvcignore", ".dvc", ".cache",
                   "artifacts", "reports")
#: what distill writes too when it makes a new project a git repository (:func:`git_outputs`)
GIT_OUTPUTS = (".git", ".gitignore")
#: the project's .gitignore (DVC adds its stage outputs to .gitignore files of their own folders)
GITIGNORE = "/.cache/\n__pycache__/\n*.pyc\n/dvc_plots/\n/geodistill_plots/\n"
#: the files of distill's first commit in a new git project (:func:`init_git`)
GIT_TRACKED = (PARAMS_FILE, DVC_FILE, PROTOCOL_FILE, RECORD_FILE, ".dvcignore", ".gitignore", ".dvc")
#: the author of that commit: the command, not the user (unsigned: no key prompt)
GIT_AUTHOR = ("-c", "user.name=geodistill distill", "-c", "user.email=geodistill@localhost", "-c", "commit.gpgsign=false")
#: DVC's last line after `dvc repro` (dvc/commands/repro.py), left out: a distill project has no remote
DVC_PUSH_HINT = "Use `dvc push` to send your updates to remote storage."
#: a distill.json written before records named their writer: recognised by these keys
LEGACY = {"legacy_outputs": PROJECT_OUTPUTS, "legacy_keys": ("input", "code", "geodistill_version")}
DVC_HEADER = """\
# The GeoDistill-Refine DAG of a `geodistill distill` project, GENERATED by that command from the
# installed code (pipeline/orchestration/dag.py): the repository's stages, with code deps as absolute paths of the
# installed files and `prepare` depending on the input folder.  Rerun the command (or `dvc repro`).
"""
PARAMS_HEADER = """\
# GeoDistill-Refine params of a `geodistill distill` project -- profile 'distill' (pipeline/profiles.py)
# with the command's --params/--set and its data and teacher options, written by `geodistill distill`
# (rerunning that command rewrites this file).  Edit single values here, then run `dvc repro` in this
# folder: DVC tracks every key, so a change reruns exactly the stages that read it.
"""


def check_folder(path: str | Path, what: Option) -> Path:
    """An existing folder as an absolute path; InputError naming the option ``what`` otherwise."""
    p = Path(path)
    if not p.exists():
        raise InputError("{}: folder not found", what(p))
    if not p.is_dir():
        raise InputError("{}: not a folder", what(p))
    return p.resolve()


def project_params(params: Mapping, input_dir: Path, val_masks: Path | None) -> dict:
    """The nested overrides that point a params set at the folder (module docstring)."""
    return {"data": {"source": "folder", "root": str(input_dir), "protocol": PROTOCOL_FILE}}


def protocol_text(input_dir: Path, val_masks: Path | None) -> str:
    """``folder_protocol.yaml``: the folder adapter's protocol (data_manifests/folder.yaml) for INPUT."""
    proto = {"dataset": "folder", "images_dir": str(input_dir),
             "masks_dir": str(val_masks) if val_masks is not None else None,
             "val_fraction": 0.5, "mask_threshold": None, "spacecraft": input_dir.name, "domain": "folder"}
    return ("# written by `geodistill distill`: the images of INPUT, and the --val-masks folder (null: none);\n"
            "# images with a mask go to validation/test (seeded halves), the others are training images\n"
            + yaml.safe_dump(proto, sort_keys=False))


def check_val_masks(input_dir: Path, masks: Path) -> int:
    """How many images of ``input_dir`` have a mask (same id: relative path without the suffix) in
    ``masks``; InputError under 2 (the folder protocol needs one validation and one test image)."""
    def ids(folder: Path) -> set[str]:  # the folder adapter's image ids: relative path without suffix
        return {f.relative_to(folder).with_suffix("").as_posix() for f in scan_inputs(folder).files}

    n = len(ids(input_dir) & ids(masks))
    if n < 2:
        raise InputError(f"{{}}: {n} mask(s) named like an image of {literal(input_dir)}; at least 2 are "
                         "needed (half validation, half test)", VAL_MASKS(masks))
    return n


def _dvc(out: Path, *args: str, env: Mapping[str, str] | None = None, capture: bool = True):
    return subprocess.run([sys.executable, "-m", "dvc", *args], cwd=out, env=dict(env or _env()),
                          capture_output=capture, text=True)


def _env(device: str = "auto") -> dict:
    env = {**os.environ, "PATH": f"{Path(sys.executable).parent}{os.pathsep}{os.environ.get('PATH', '')}",
           "DVC_NO_ANALYTICS": "1"}
    if device == "cpu":
        env["CUDA_VISIBLE_DEVICES"] = ""
    if bars_quiet():  # distill --quiet: the stages DVC runs draw no bars either
        env[QUIET_ENV] = "1"
    return env


def write_project(input_dir: str | Path, out: str | Path, params: Mapping, *,
                  val_masks: str | Path | None = None, overwrite: bool = False,
                  labels: str | Path | None = None, benchmark: bool = True) -> Path:
    """Create or update the DVC project in ``out`` for ``input_dir`` (module docstring); returns ``out``.
    ``labels``: the label folder ``params`` were taken from (:func:`pipeline.api.params_from_labels`),
    recorded in distill.json.  ``benchmark=False`` (``--no-benchmark``): no benchmark stage in dvc.yaml.

    ``params``: validated params (the distill profile with the user's overrides and the teacher).  In
    an existing ``out``, every path of :data:`PROJECT_OUTPUTS` that exists must be listed by a
    ``distill.json`` of an earlier run, unless ``overwrite`` (:mod:`pipeline.artifacts.ownership`)."""
    input_dir = check_folder(input_dir, INPUT)
    find_images(input_dir)  # one line when there is no image at all
    masks = check_folder(val_masks, VAL_MASKS) if val_masks is not None else None
    if masks is not None:
        check_val_masks(input_dir, masks)
    out = Path(out)
    if out.resolve() == input_dir or input_dir in out.resolve().parents:
        raise InputError("{}: must not be the input folder or inside it", OUT(out))
    if params["teacher"]["backend"] == "simulated":
        raise InputError("{}: the SIMULATOR reads ground-truth masks of the training images, which a folder of "
                         "images has not; use {} or {}", BACKEND("simulated"), CHECKPOINT("SAM3_DIR"),
                         BACKEND("imported"))
    git = git_outputs(out)
    check_outputs(out, PROJECT_OUTPUTS + git, RECORD_FILE, "distill", overwrite=overwrite, **LEGACY)
    refuse_foreign_outputs(out)
    out.mkdir(parents=True, exist_ok=True)
    out = out.resolve()
    record = {"input": str(input_dir), "val_masks": str(masks) if masks is not None else None,
              "teacher_backend": params["teacher"]["backend"], "teacher_checkpoint": params["teacher"]["checkpoint"],
              "labels": str(Path(labels).resolve()) if labels is not None else None,
              "code": str(ROOT), "geodistill_version": __version__,
              **record_fields(out, RECORD_FILE, "distill", PROJECT_OUTPUTS + git, **LEGACY)}
    write_text_if_changed(out / RECORD_FILE, json.dumps(record, indent=1, sort_keys=True) + "\n")  # first

    text = render_params_yaml(PROFILE, deep_merge(dict(params), project_params(params, input_dir, masks)),
                              header=PARAMS_HEADER)
    write_text_if_changed(out / PARAMS_FILE, text)
    write_text_if_changed(out / PROTOCOL_FILE, protocol_text(input_dir, masks))
    data_deps = {"prepare": [PROTOCOL_FILE, str(input_dir)] + ([str(masks)] if masks is not None else [])}
    omit = (() if masks is not None else NO_MASK_STAGES) + (() if benchmark else (BENCHMARK_STAGE,))
    # without masks the evaluate stage's plots are omitted: `dvc plots show` shows the runs' DVCLive loss
    extra = live_plots(params["protocol"]["runs"]) if masks is None else []
    write_text_if_changed(out / DVC_FILE, render_dvc_yaml(code_root=ROOT, data_deps=data_deps, header=DVC_HEADER,
                                                        omit=omit, extra_plots=extra))
    write_text_if_changed(out / ".dvcignore", DVCIGNORE)
    new_git = bool(git) and init_git(out)
    if not (out / ".dvc").is_dir():
        scm = new_git or ((out / ".git").is_dir() and ".git" in record["outputs"])  # a git init of a killed run
        for args in (("init", "-q") if scm else ("init", "--no-scm", "-q"), ("config", "core.analytics", "false"),
                     *([("config", "core.autostage", "true")] if scm else [])):
            res = _dvc(out, *args)
            if res.returncode != 0:
                raise InputError(f"{{}}: `dvc {literal(' '.join(args))}` failed: "
                                 f"{literal((res.stderr or res.stdout).strip().splitlines()[-1:])}", OUT(out))
    # after `dvc init` (which a pre-made .dvc/ would skip): dvc.yaml's plots name this template, and
    # without it `dvc plots show` fails in the project
    write_text_if_changed(template_path(out), template_text())
    if new_git:
        commit_project(out)
    return out


def dvc_folder_files(project: Path, lock: Mapping, rel: str) -> set[str] | None:
    """The files (relative, posix) DVC recorded in the output folder ``rel`` of ``project``: its dvc.lock
    entry's ``.dir`` listing in the project's cache; None when DVC recorded none (no entry, not cached)."""
    for stage in (lock.get("stages") or {}).values():
        for o in stage.get("outs") or []:
            md5 = str(o.get("md5", ""))
            if o.get("path") != rel or not md5.endswith(".dir"):
                continue
            for cache in (project / ".dvc" / "cache" / "files" / "md5", project / ".dvc" / "cache"):  # DVC 3, 2
                try:
                    listing = json.loads((cache / md5[:2] / md5[2:]).read_text())
                except (OSError, ValueError):
                    continue
                return {str(e["relpath"]) for e in listing if isinstance(e, dict) and "relpath" in e}
    return None


def refuse_foreign_outputs(out: str | Path) -> None:
    """Refuse (InputError naming it, ``--overwrite`` or not) a file inside an output folder of the DAG
    that the DAG did not write: ``dvc repro`` replaces such a folder whole, so the file would be lost.
    The DAG's own files are those DVC recorded there (:func:`dvc_folder_files`); for the deploy bundle,
    without a record, those export recognises as its bundle's (:func:`pipeline.deploy.export.bundle_files`,
    export's own check: :func:`pipeline.artifacts.ownership.refuse_foreign_files`).  Other folders without a record
    are left to DVC (a run killed half-way leaves the stage's own files there)."""
    out = Path(out)
    try:
        lock = yaml.safe_load((out / "dvc.lock").read_text()) or {}
    except (OSError, yaml.YAMLError):
        lock = {}
    deploy = catalog.path("deploy", Path(catalog.ARTIFACTS_DIR)).as_posix()
    folders = {str(o.get("path")) for st in (lock.get("stages") or {}).values() for o in st.get("outs") or []
               if str(o.get("md5", "")).endswith(".dir")} | {deploy}
    for rel in sorted(folders):
        own = dvc_folder_files(out, lock, rel)
        if rel == deploy:
            own = (own or set()) | bundle_files(out / rel)
        if own is not None:
            refuse_foreign_files(out / rel, own, command="distill", option=OUT, where=out,
                                 why=f"not written there by the pipeline, and `dvc repro` replaces {rel}/ whole")


def git_outputs(out: Path) -> tuple[str, ...]:
    """:data:`GIT_OUTPUTS` when ``out`` is to become a new git project (git is installed and ``out`` has
    none of ``.dvc``, ``.git``, ``.gitignore``: a project made before stays ``--no-scm``, a repository or
    .gitignore of the user's is left alone), else ()."""
    if shutil.which("git") is None or any((Path(out) / f).exists() for f in (".dvc", *GIT_OUTPUTS)):
        return ()
    return GIT_OUTPUTS


def init_git(out: Path) -> bool:
    """``git init`` in the new project folder ``out`` and its ``.gitignore``; True when done (False,
    with a warning, when git fails: the project is then ``--no-scm``)."""
    res = subprocess.run(["git", "init", "-q", str(out)], capture_output=True, text=True)
    if res.returncode != 0:
        log.warning("distill: `git init` failed in %s (%s); the project is --no-scm", out, res.stderr.strip())
        return False
    write_text_if_changed(out / ".gitignore", GITIGNORE)
    return True


def commit_project(out: Path) -> None:
    """One commit of distill's project files (:data:`GIT_TRACKED`) in the git repository :func:`init_git`
    made, by "geodistill distill": ``dvc exp`` needs a commit to start from."""
    tracked = [f for f in GIT_TRACKED if (out / f).exists()]
    for args in (("add", "--", *tracked), (*GIT_AUTHOR, "commit", "-q", "--no-verify", "-m",
                                           "geodistill distill: the project")):
        res = subprocess.run(["git", *args], cwd=out, capture_output=True, text=True)
        if res.returncode != 0:
            log.warning("distill: `git %s` failed in %s: %s", args[0] if args[0] != "-c" else "commit", out,
                        res.stderr.strip())
            return


#: a stage's own one-line error (stages._common.one_line_errors) and DVC's lines about a failed stage
_STAGE_ERROR = re.compile(r"^geodistill [\w-]+: error: (.*)$")
_DVC_ERROR = re.compile(r"^ERROR: ")


def run_project(out: str | Path, device: str = "auto", quiet: bool = False) -> None:
    """``dvc repro`` in the project ``out``, its output streamed.  When a stage fails, its own one-line
    message is held back and raised once (InputError, the flags it names spelled again in the caller's
    terms: :meth:`pipeline.runtime.errors.InputError.from_line`), with DVC's ``ERROR: failed to reproduce ...``
    left out; a stage that failed without such a line (a bug: its traceback is shown) is reported by
    DVC's line.  ``quiet`` (``--quiet``): ``dvc repro -q`` and the stages' step log at WARNING (unless
    ``GEODISTILL_LOG`` says otherwise)."""
    out = Path(out)
    env = _env(device)
    if quiet:  # --quiet: warnings, errors and the summary only -- no DVC stage lines, no INFO step log
        env.setdefault("GEODISTILL_LOG", "WARNING")
    proc = subprocess.Popen([sys.executable, "-m", "dvc", "repro", *(["-q"] if quiet else [])], cwd=out, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, errors="replace")
    relay = threading.Thread(target=_relay_stdout, args=(proc.stdout,), daemon=True)
    relay.start()
    stage_error = dvc_error = None
    for line in proc.stderr:
        if (m := _STAGE_ERROR.match(line.rstrip("\n"))) is not None:
            stage_error = m.group(1)
        elif _DVC_ERROR.match(line):
            dvc_error = dvc_error or line.strip()
        else:
            sys.stderr.write(line)
            sys.stderr.flush()
    rc = proc.wait()
    relay.join()
    if rc != 0:
        if stage_error is not None:
            raise InputError.from_line(stage_error)
        raise InputError(f"{out}: {dvc_error or f'dvc repro failed (exit {rc})'}; the stage's output is above -- "
                         "fix it and rerun the same command to resume")


def _relay_stdout(stream) -> None:
    """``dvc repro``'s standard output to ours, line by line, without :data:`DVC_PUSH_HINT`."""
    for line in stream:
        if line.strip() != DVC_PUSH_HINT:
            sys.stdout.write(line)
            sys.stdout.flush()


def project_outputs(out: str | Path) -> dict[str, Path]:
    """Where a finished project's results are: deploy bundle, report, thresholds, checkpoints."""
    out = Path(out)
    art = out / catalog.ARTIFACTS_DIR
    profile = read_yaml_mapping(out / PARAMS_FILE).get("profile", PROFILE)
    return {"deploy": catalog.path("deploy", art), "report": catalog.path("report", art, profile=profile) / catalog.output_file("report", "html"),
            "thresholds": catalog.path("thresholds", art), "checkpoints": catalog.path("checkpoints", art)}


#: below this teacher-vote Image IoU distill prints no efficiency ratio: over a vote that found almost
#: nothing, the ratio is large and means nothing (47.5 x a vote of IoU 0.004)
MIN_VOTE_IOU = 0.05


def efficiency_line(out: str | Path) -> str | None:
    """The summary line of a finished project whose held-out images have masks (``--val-masks``): the
    deployed student's (``deploy.export_method``) distillation efficiency as a ratio with its meaning,
    "0.93 × the teacher vote's Image IoU" -- its test Image IoU at the calibrated tau over the teacher
    vote's on the same images (the report stage's ``metrics_efficiency`` files,
    :func:`pipeline.report.dvc_results.efficiency_metric_files`), per group when there are several.  A group
    whose vote IoU is below :data:`MIN_VOTE_IOU` gets no ratio, and the line says why.  None when there
    is no such file (no masks, or no test image)."""
    out = Path(out)
    art = out / catalog.ARTIFACTS_DIR
    method = str((read_yaml_mapping(out / PARAMS_FILE).get("deploy") or {}).get("export_method", PROPOSED))
    found = []
    for f in sorted(catalog.path("metrics_efficiency", art).glob(f"*/{path_component(method)}.json")):
        group = f.parent.name
        eff = _metric(f, "efficiency")
        if eff is not None:
            found.append((group, eff, _metric(catalog.path("metrics_students", art) / group / f.name, "iou"),
                          _metric(catalog.path("metrics_teacher", art) / f"{group}.json", "iou")))
    if not found:
        return None
    name = method_label(method)
    low = [(g, vote) for g, _, _, vote in found if vote is not None and vote < MIN_VOTE_IOU]
    kept = [row for row in found if row[0] not in {g for g, _ in low}]
    why = ("; no ratio for " + ", ".join(g for g, _ in low) + ": the teacher vote's Image IoU there is "
           + ", ".join(f"{v:.3f}" for _, v in low) + f", below {MIN_VOTE_IOU:g}, so the teacher found almost "
           "nothing to distil and a ratio would mean nothing") if low and kept else ""
    if not kept:
        vote = ", ".join(f"{v:.3f}" for _, v in low)
        return (f"no distillation efficiency: the teacher vote's test Image IoU is {vote}, below {MIN_VOTE_IOU:g} "
                f"(the teacher found almost nothing on the held-out images with masks), so a ratio to it would "
                f"mean nothing; {name}'s own test Image IoU is in the report")
    if len(kept) == 1 and len(found) == 1 and None not in kept[0]:
        _, e, iou, vote = kept[0]
        return (f"the student's test Image IoU is {e:.2f} × the teacher vote's Image IoU ({name}: {iou:.3f}; the "
                f"vote: {vote:.3f}, on the same held-out images with masks)")
    ratios = ", ".join(f"{e:.2f} ×" + (f" ({g})" if len(found) > 1 else "") for g, e, _, _ in kept)
    return (f"the student's test Image IoU is {ratios} the teacher vote's Image IoU ({name}, on the same "
            f"held-out images with masks){why}")


def training_line(out: str | Path) -> str | None:
    """The summary line of a finished project's Stage I (the Plain Student of the first seed): optimizer
    steps run, and why it stopped (``train.until: plateau``); None without its checkpoint record."""
    out = Path(out)
    runs = (read_yaml_mapping(out / PARAMS_FILE).get("protocol") or {}).get("runs") or {}
    seeds = runs.get(STAGE_ONE) or []
    if not seeds:
        return None
    meta = catalog.path("checkpoints", out / catalog.ARTIFACTS_DIR) / STAGE_ONE / str(seeds[0]) / catalog.META_FILE
    try:
        extra = json.loads(meta.read_text()).get("extra") or {}
    except (OSError, ValueError):
        return None
    if "steps_run" not in extra:
        return None
    why = f", stopped at {extra['stopped']}" if extra.get("stopped") else " (its fixed length)"
    return f"Stage I trained {int(extra['steps_run']):,} optimizer steps ({extra.get('epochs')} epochs){why}"


def _metric(path: Path, key: str) -> float | None:
    """``key`` of the DVC metrics file ``path`` (pipeline.report.dvc_results), None when either is absent."""
    try:
        value = json.loads(path.read_text()).get(key)
    except (OSError, ValueError):
        return None
    return float(value) if isinstance(value, (int, float)) else None


def time_budget_params(params: dict, time_budget: str | None, out: str | Path, device: str = "auto") -> dict:
    """``params`` with ``--time`` / ``time=`` as Stage I's step budget (:func:`pipeline.training.budget.with_time_budget`),
    reusing the steps the project ``out`` already recorded for the same time."""
    if time_budget is None:
        return params
    previous = read_yaml_mapping(Path(out) / PARAMS_FILE) if (Path(out) / PARAMS_FILE).is_file() else None
    return with_time_budget(params, time_budget, previous, resolve_device(device).type)


