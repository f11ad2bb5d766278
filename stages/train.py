"""Stage ``train`` (DVC: ``train_<method>@<seed>``): train one (method, seed) student.

    python -m stages.train --stage 1|2 --method M --seed S --artifacts artifacts \
        [--init artifacts/checkpoints/plain/S] --out artifacts/checkpoints/M/S

* Which (M, S) runs exist is params.yaml's ``protocol.runs``; dvc.yaml has a stage for exactly those.
* ``--init`` is the Stage-I checkpoint for warm-started methods (``geodistill``, ``sdf_*_gated``,
  ``no_gate``, ``geodistill_adaptive``); methods trained from scratch (``gabi``, ``*_scratch*``,
  Stage-I methods) ignore it and do not record it in their lineage.
* Per-epoch resume state lives under ``--resume-dir``/<checkpoint fingerprint> (default
  ``.cache/train``, outside DVC outs): a killed run continues where it stopped; a finished one reruns
  instantly.  The fingerprint holds every ``train.*`` key the method reads, the execution knobs
  ``train.num_threads`` and ``train.precision`` among them, so a changed thread count trains afresh.
* The epoch rows are also logged with DVCLive into ``--live-dir`` (dvc.yaml: ``reports/dvclive/<M>/<S>``, a
  git-tracked out; :func:`pipeline.dvc_results.write_live_log`): ``dvc plots show reports/dvclive/<M>/<S>/plots/metrics/val_iou.tsv``
  or any DVCLive-aware viewer reads it.  The checkpoint's log.parquet stays the typed artifact the
  report and evaluate read.
* Exit codes: 0 ok; 2 bad input (one line naming the file or parameter); 1 training diverged
  (non-finite loss; one line, no checkpoint written).

Wiring only: this module opens the artifacts under ``--artifacts``
(:func:`pipeline.training_inputs.load_inputs`), the
``--init`` checkpoint (:func:`load_init`) and the resume state
(:class:`pipeline.checkpointing.FileCheckpointer`), and logs the epoch rows
(:func:`pipeline.dvc_results.write_live_log`);
:func:`pipeline.training.train` gets arrays and a checkpointer.  Reference masks (reference.zarr)
are opened only for :func:`pipeline.training.validation_data` (checkpoint selection).
"""

from __future__ import annotations

import sys
from pathlib import Path

import click

from pipeline import catalog
from pipeline.artifacts import open_artifact, write_json
from pipeline.catalog import ARTIFACTS_DIR
from pipeline.checkpointing import FileCheckpointer
from pipeline.device import resolve_device
from pipeline.dvc_results import write_live_log
from pipeline.environment import training_runtime
from pipeline.errors import ArtifactError, InputError, TrainingDiverged
from pipeline.inference import load_student, save_checkpoint
from pipeline.methods import SELECTION_TAU_KEY, SUPERVISED_CEILING, fingerprint_params, get_method
from pipeline.params import get_path, section
from pipeline.training_inputs import load_inputs
from stages._common import stage_command, stage_context


def load_init(path: str | Path):
    """Stage-I checkpoint for a warm start: (mask-path state dict, its artifact for the lineage)."""
    p = Path(path)
    if not (p / "meta.json").exists():
        raise ArtifactError(f"--init {p}: not a checkpoint directory (run train_plain first)")
    art = open_artifact(p, "checkpoint")
    model, _ = load_student(p)
    return model.mask_path_state_dict(), art


def run(params: dict, device: str, stage: int, method: str, seed: int, artifacts: str, init: str | None,
        out: str, resume_dir: str, live_dir: str | None = None) -> Path:
    cfg = section(params, "train")
    spec = get_method(method)
    if spec.stage != stage:
        raise InputError(f"--stage {stage}: method {method!r} belongs to --stage {spec.stage}")
    if not spec.annotation_free and not params["protocol"][SUPERVISED_CEILING]:
        raise InputError(f"--method {method}: trains on reference masks (not annotation-free); "
                         f"needs params protocol.{SUPERVISED_CEILING}: true")
    from pipeline import training  # torch: imported once the options are checked

    data, val, inputs = load_inputs(artifacts, spec, cfg, review=section(params, "review"))
    init_state = None
    if spec.init == "stage1":
        if not init:
            raise InputError(f"--init missing: method {method!r} warm-starts from a Stage-I checkpoint")
        init_state, init_art = load_init(init)
        inputs.append(init_art)
    meta = stage_context("train", __file__, params).meta(
        "checkpoint", inputs, params={"params": fingerprint_params(spec, params), "method": method, "seed": seed,
                                      "stage": stage}, **data.stats)
    result = training.train(spec, cfg, data, val, seed, init_state=init_state, device=resolve_device(device),
                            checkpointer=FileCheckpointer(Path(resume_dir) / meta.fingerprint),
                            selection_tau=get_path(params, SELECTION_TAU_KEY))
    meta.extra.update(result.info)  # info["autocast"]: the precision actually used
    meta.extra["runtime"] = training_runtime(resolve_device(device))  # provenance, not fingerprinted
    save_checkpoint(out, result.model, meta, result.log, method=method, seed=seed, stage=stage,
                    selected_epoch=result.selected_epoch, selection=result.info["selection"],
                    resolution=int(data.images.shape[1]),
                    mode=result.info["mode"], fingerprint=meta.fingerprint)
    write_live_log(result.log, live_dir or catalog.path("train_live", artifacts, method=method, seed=seed),
                   result.selected_epoch)
    # wall clock beside, not inside, the checkpoint: the checkpoint is byte-identical on a rerun
    write_json(catalog.path("train_timings", artifacts, method=method, seed=seed),
               {"method": method, "seed": seed, "device": str(resolve_device(device)), "epochs": result.timings})
    click.echo(f"train: {method} seed {seed}: selected epoch {result.selected_epoch} "
               f"({result.info['selection']}); wrote {out}", err=True)
    return Path(out)


@stage_command("train")
@click.option("--stage", type=click.IntRange(1, 2), required=True, help="1 (Stage-I methods) or 2")
@click.option("--method", required=True, help="plain, geodistill, ... (pipeline.methods.METHODS)")
@click.option("--seed", type=int, required=True)
@click.option("--artifacts", default=ARTIFACTS_DIR, show_default=True, type=click.Path(file_okay=False))
@click.option("--init", default=None, help="Stage-I checkpoint dir (warm-started methods only; others ignore it)")
@click.option("--out", required=True, help="checkpoint directory to write")
@click.option("--resume-dir", default=".cache/train", show_default=True,
              help="per-epoch resume states (outside DVC outs)")
@click.option("--live-dir", default=None,
              help="DVCLive log of the epoch rows (default: reports/dvclive/<method>/<seed> beside the artifacts dir)")
def main(params, device, stage, method, seed, artifacts, init, out, resume_dir, live_dir):
    """Train one (method, seed) student on pseudo-targets; write checkpoint + training log."""
    try:
        run(params, device, stage, method, seed, artifacts, init, out, resume_dir, live_dir)
    except TrainingDiverged as e:
        click.echo(f"geodistill train: training diverged: {str(e).splitlines()[0]}", err=True)
        sys.exit(1)


if __name__ == "__main__":
    main()
