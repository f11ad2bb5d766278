"""Where does the student's validation Image IoU plateau?  One stable-phase run of the ``wsd`` schedule saves its
state at E0, 2 E0, 4 E0, ... epochs; a decay branch from each gives the run of that length, scored on the
validation images at their calibrated tau.  The plateau is the first length whose next doubling gains less than
``--plateau-gain``; the test images are scored once, there.  States and branches are kept: more doublings continue.

    python -m benchmarks.convergence --profile reduced --recipe paper --seed 42 --out convergence.json
"""

from __future__ import annotations

import json
import time
from pathlib import Path
from typing import Any, Mapping

from pipeline.artifacts.lineage import fingerprint
from pipeline.training.checkpointing import FileCheckpointer
from pipeline.runtime.device import resolve_device
from pipeline.methods import STAGE_ONE, SUPERVISED_CEILING, get_method, method_lr
from pipeline.profiles import load_profile
from benchmarks.common import parser, read_json, seconds
from benchmarks.study_recipe import build_artifacts, load_study_data, score_run

#: a doubling of the optimizer steps that gains less validation Image IoU than this is the plateau
PLATEAU_GAIN = 0.005


def branch_epochs(first: int, doublings: int) -> list[int]:
    """The stable-phase epochs where decay branches start: first x 2^k, k = 0..doublings."""
    return [int(first) * 2 ** k for k in range(int(doublings) + 1)]


def decay_epochs(stable: int, fraction: float) -> int:
    """Epochs of the decay after ``stable`` epochs: ``fraction`` of the whole run, at least one."""
    return max(1, int(round(stable * fraction / (1.0 - fraction))))


def plateau(values: list[float], gain: float = PLATEAU_GAIN) -> int | None:
    """Index of the first of ``values`` (one per doubling) whose next gains less than ``gain``; None if none."""
    for i in range(len(values) - 1):
        if values[i + 1] - values[i] < gain:
            return i
    return None


class BranchStore:
    """The stable run's checkpointer: its full state at each branch epoch, on disk, and the decay branches'
    final weights.  A longer stable run resumes from the latest state of a shorter one (the stable phase
    does not depend on the run's length): only the run key's ``epochs`` may differ."""

    def __init__(self, directory: str | Path, epochs: list[int]) -> None:
        self.directory, self.epochs = Path(directory), sorted(int(e) for e in epochs)

    def _file(self, phase: str, epoch: int) -> FileCheckpointer:
        return FileCheckpointer(self.directory / f"{phase}-{int(epoch):05d}")

    def state(self, epoch: int) -> dict | None:
        return self._file("stable", epoch).load(None)

    def load(self, run_key):
        saved = (self.state(e) for e in reversed(self.epochs) if e <= int(run_key["epochs"]))
        state = next((s for s in saved if s is not None), None)
        if state is None or {**state["run_key"], "epochs": 0} != {**run_key, "epochs": 0}:  # epochs may differ
            return None
        return {**state, "run_key": dict(run_key)}

    def save(self, state: dict) -> None:
        if state["epoch"] in self.epochs:
            self._file("stable", state["epoch"]).save(state)

    def save_weights(self, epoch: int, model) -> None:
        weights = {k: v.detach().cpu() for k, v in model.state_dict().items()}
        self._file("decay", epoch).save({"epoch": int(epoch), "model": weights})

    def weights(self, epoch: int) -> dict | None:
        return (self._file("decay", epoch).load(None) or {}).get("model")


class _StartFrom:
    """A checkpointer that starts a run from a saved stable-phase state with a fresh schedule and log."""

    def __init__(self, state: Mapping[str, Any], lr: float) -> None:
        import torch

        from pipeline.training.loop import STATE_VERSION

        self.state, self.version = state, STATE_VERSION
        dummy = torch.optim.AdamW([torch.zeros(1, requires_grad=True)], lr=lr)
        self.scheduler = torch.optim.lr_scheduler.LambdaLR(dummy, lambda step: 1.0).state_dict()

    def load(self, run_key):
        s = self.state
        return {"version": self.version, "run_key": run_key, "epoch": 0, "model": s["model"],
                "optimizer": s["optimizer"], "scheduler": self.scheduler, "torch_rng": s["torch_rng"],
                "log": [], "best": None}

    def save(self, state: dict) -> None:
        pass


def study_method(method: str, cfg: Mapping[str, Any], data, val, seed: int, branches: list[int],
                 fraction: float, device: str, store: BranchStore, done: Mapping[int, dict] | None = None) -> list[dict]:
    """One method's curve: each branch's validation scores (those in ``done`` kept); the stable phase runs
    only when a new branch's state is not in ``store``."""
    from pipeline.training import loop as training
    done = done or {}
    spec = get_method(method)
    todo = [e for e in branches if e not in done]
    steps_per_epoch = max(1, -(-len(data) // int(cfg["batch_size"])))
    stable_s: dict = {}  # the stable phase this session ran, up to max(todo): on the first new branch
    if any(store.state(e) is None for e in todo):
        stable = {**cfg, "epochs_stage1": max(todo), "schedule": "constant", "average_last": 0}
        stable_s["stable_seconds"] = seconds(lambda: training.train(spec, stable, data, val, seed, checkpointer=store,
                                                                    device=device, show_progress=False))
    curve = []
    for e in branches:
        if e in done:
            curve.append(dict(done[e]))
            continue
        d = decay_epochs(e, fraction)
        decay = {**cfg, "epochs_stage1": d, "schedule": "wsd", "decay_fraction": 1.0, "warmup_epochs": 0,
                 "average_last": 1}  # the branch's last weights, BN statistics recomputed
        t1 = time.perf_counter()
        res = training.train(spec, decay, data, val, seed, checkpointer=_StartFrom(store.state(e), method_lr(spec, cfg)),
                             device=device, show_progress=False)
        store.save_weights(e, res.model)
        scores = training.validation_scores(res.model, val, device, precision="fp32", channels_last=False,
                                            tolerance=float(cfg["val_bf1_tolerance"]))
        curve.append({"stable_epochs": e, "decay_epochs": d, "epochs": e + d, "steps": (e + d) * steps_per_epoch,
                      "val_iou_cal": scores["val_iou_cal"], "val_tau_cal": scores["val_tau_cal"],
                      "val_iou_05": scores["val_iou"], "val_bf1_05": scores["val_bf1"],
                      "decay_seconds": time.perf_counter() - t1, **stable_s})
        stable_s = {}
    return curve


def main(argv=None) -> dict:
    ap = parser(__doc__, artifacts=None, workdir="convergence", profile="reduced", set=[], threads=2, device="cpu",
                out="convergence.json")
    ap.add_argument("--recipe", default="paper", help="train.recipe of the branches (paper | stable | strong)")
    ap.add_argument("--methods", nargs="+", default=[STAGE_ONE, SUPERVISED_CEILING])
    ap.add_argument("--seed", type=int, default=42)
    ap.add_argument("--first", type=int, default=5, help="stable epochs of the shortest branch")
    ap.add_argument("--doublings", type=int, default=5, help="branches at first x 2^k, k = 0..doublings")
    ap.add_argument("--decay-fraction", type=float, default=None, help="default: train.decay_fraction")
    ap.add_argument("--plateau-gain", type=float, default=PLATEAU_GAIN)
    ap.add_argument("--states", default=None,
                    help="where the branch states and weights are kept (default: <workdir>/branch_states)")
    args = ap.parse_args(argv)

    from pipeline.training.loop import build_model

    device = str(resolve_device(args.device))
    params = load_profile(args.profile, [f"train.recipe={args.recipe}", *args.sets])
    artifacts = Path(args.artifacts) if args.artifacts else \
        build_artifacts(Path(args.workdir).resolve(), args.profile, list(args.sets), device)
    cfg = {**params["train"], "num_threads": args.threads}
    fraction = float(args.decay_fraction if args.decay_fraction is not None else cfg["decay_fraction"])
    branches = branch_epochs(args.first, args.doublings)
    out_path = Path(args.out)
    doc = read_json(out_path)
    if not isinstance(doc, dict) or (doc and not isinstance(doc.get("info"), dict)):
        ap.error(f"--out {out_path}: exists and is not a convergence study; give another --out")
    info = {"profile": args.profile, "recipe": args.recipe, "sets": args.sets, "seed": args.seed,
            "resolution": int(params["data"]["resolution"]), "decay_fraction": fraction,
            "plateau_gain": args.plateau_gain, "device": device, "threads": args.threads}
    if doc and {k: v for k, v in doc.get("info", {}).items() if k != "branches"} != info:
        ap.error(f"--out {out_path}: holds a study with other settings; give another --out")
    doc["info"] = {**info, "branches": branches}
    data = load_study_data(artifacts, cfg, methods=tuple(args.methods))
    data_id = {"profile": args.profile, "sets": args.sets, "artifacts": str(artifacts.resolve()), "fraction": fraction}
    states = Path(args.states) if args.states else Path(args.workdir).resolve() / "branch_states"
    for m in args.methods:
        prev = doc.get("methods", {}).get(m, {})
        done = {c["stable_epochs"]: c for c in prev.get("curve", [])}
        if all(e in done for e in branches) and prev.get("branches") == branches:
            print(f"{m}: done already in {out_path}", flush=True)
            continue
        # a run's states: method, seed and a digest of the training config and the data
        digest = fingerprint("convergence", "", {"cfg": cfg, "data": data_id}, [])[:12]
        store = BranchStore(states / f"{m}-s{args.seed}-{digest}", branches)
        curve = study_method(m, cfg, data[m], data["val"], args.seed, branches, fraction, device, store, done)
        i = plateau([c["val_iou_cal"] for c in curve], args.plateau_gain)
        chosen = curve[i if i is not None else -1]
        weights = store.weights(chosen["stable_epochs"])
        if weights is None:  # a branch scored before its weights were kept: run that decay again
            study_method(m, cfg, data[m], data["val"], args.seed, [chosen["stable_epochs"]], fraction, device, store)
            weights = store.weights(chosen["stable_epochs"])
        model = build_model(get_method(m), cfg, args.seed)  # the study's methods train from scratch
        model.load_state_dict(weights)
        model.eval()
        test = score_run(model, data["val"], data["test_images"], data["test_masks"], device)  # the chosen length only
        doc.setdefault("methods", {})[m] = {
            "branches": branches, "curve": [dict(c) for c in curve],
            "plateau_index": i, "plateau_steps": chosen["steps"] if i is not None else None,
            "chosen_epochs": chosen["epochs"], "test_iou": test["iou_cal"], "test_tau": test["tau_cal"]}
        out_path.write_text(json.dumps(doc, indent=1))  # partial results survive an interruption
        print(f"{m}: " + ", ".join(f"{c['steps']} steps {c['val_iou_cal']:.3f}" for c in curve)
              + f"; plateau {'at ' + str(chosen['steps']) + ' steps' if i is not None else 'not reached'}; "
              f"test IoU {test['iou_cal']:.3f} (scored once, at the chosen length)", flush=True)
    return doc


if __name__ == "__main__":
    main()
