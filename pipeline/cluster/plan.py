"""What ``geodistill run`` submits, in which order, with which Ray resources.

Pure functions of the outputs of ``dvc dag --dot`` and ``dvc status --json``.  A stage graph ``needs`` maps each
stage to the set of its direct upstream stages.
"""

from __future__ import annotations

import dataclasses
import re
from typing import Iterable, Mapping

from pipeline.catalog import STAGES

__all__ = ["parse_dot", "to_submit", "subgraph", "run_alone", "submission_order", "startable", "Sizing",
           "stage_resources", "outcome", "error_line"]

_EDGE = re.compile(r'^\s*"([^"]+)"\s*->\s*"([^"]+)"\s*;?\s*$')
_NODE = re.compile(r'^\s*"([^"]+)"\s*;?\s*$')
TEACHER_STAGE = "teacher"  # one whole GPU per task
TRAIN_PREFIX = "train_"  # train_<method>@<seed>: a fraction of a GPU each


def parse_dot(text: str) -> tuple[list[str], dict[str, set[str]]]:
    """Read the stage graph from the output of ``dvc dag --dot``; ``.dvc`` file nodes are dropped.

    Parameters
    ----------
    text : str
        The DOT text: ``"a" -> "b"`` edge lines and ``"a"`` node lines; other lines are ignored.

    Returns
    -------
    order : list[str]
        The stages in DVC's order (first mention).
    needs : dict[str, set[str]]
        Each stage's direct upstream stages.
    """
    order: list[str] = []
    needs: dict[str, set[str]] = {}

    def node(n: str) -> None:
        if n not in needs:
            needs[n] = set()
            order.append(n)

    for line in text.splitlines():
        if m := _EDGE.match(line):
            node(m[1]), node(m[2])
            needs[m[2]].add(m[1])
        elif m := _NODE.match(line):
            node(m[1])
    keep = [n for n in order if not n.endswith(".dvc")]
    return keep, {n: {u for u in needs[n] if u in needs and not u.endswith(".dvc")} for n in keep}


def _children(needs: Mapping[str, set[str]]) -> dict[str, set[str]]:
    """Invert a stage graph: each stage's direct downstream stages."""
    children: dict[str, set[str]] = {n: set() for n in needs}
    for n, ups in needs.items():
        for u in ups:
            children[u].add(n)
    return children


def _reach(edges: Mapping[str, Iterable[str]], roots: Iterable[str]) -> set[str]:
    """Collect ``roots`` and every node reachable from them along ``edges``."""
    seen, todo = set(), list(roots)
    while todo:
        n = todo.pop()
        if n not in seen:
            seen.add(n)
            todo.extend(edges.get(n, ()))
    return seen


def downstream(needs: Mapping[str, set[str]], roots: Iterable[str]) -> set[str]:
    """Collect ``roots`` and every stage that depends on one of them, directly or not."""
    return _reach(_children(needs), [r for r in roots if r in needs])


def upstream(needs: Mapping[str, set[str]], roots: Iterable[str]) -> set[str]:
    """Collect ``roots`` and every stage they depend on, directly or not."""
    return _reach(needs, roots)


def to_submit(needs: Mapping[str, set[str]], stale: Iterable[str], targets: Iterable[str] = ()) -> set[str]:
    """Choose the stages to check with ``dvc repro``: the stale ones and everything downstream of them.

    DVC decides at each one's turn whether it runs; a downstream stage may turn out up to date.

    Parameters
    ----------
    needs : Mapping[str, set[str]]
        The stage graph.
    stale : Iterable[str]
        The stages ``dvc status`` reports changed.
    targets : Iterable[str], optional
        The stages asked for; given: the choice is kept within them and their upstream stages.

    Returns
    -------
    set[str]
        The stages to submit.
    """
    chosen = downstream(needs, stale)
    targets = list(targets)
    return chosen & upstream(needs, targets) if targets else chosen


def subgraph(needs: Mapping[str, set[str]], keep: set[str]) -> dict[str, set[str]]:
    """Restrict a stage graph to ``keep``: a kept stage waits for every kept stage upstream of it.

    Parameters
    ----------
    needs : Mapping[str, set[str]]
        The stage graph.
    keep : set[str]
        The stages kept (keys of ``needs``).

    Returns
    -------
    dict[str, set[str]]
        The graph of ``keep``, each stage needing its kept upstream stages, direct or not.
    """
    return {n: upstream(needs, needs[n]) & keep for n in keep}


def exclusive_stage(name: str) -> bool:
    """Tell whether a stage measures wall time (the catalogue's ``exclusive``); ``@seed`` suffixes ignored."""
    spec = STAGES.get(name.split("@", 1)[0])
    return bool(spec and spec.exclusive)


def run_alone(needs: Mapping[str, set[str]]) -> dict[str, set[str]]:
    """Order each exclusive stage after every stage that does not depend on it, so that nothing runs beside it.

    Parameters
    ----------
    needs : Mapping[str, set[str]]
        The stage graph.

    Returns
    -------
    dict[str, set[str]]
        A new graph: an exclusive stage (:attr:`pipeline.catalog.StageSpec.exclusive`) also needs every
        non-exclusive stage outside its downstream.
    """
    out = {n: set(u) for n, u in needs.items()}
    for x in (n for n in needs if exclusive_stage(n)):
        after = downstream(needs, [x])
        out[x] |= {n for n in needs if n not in after and not exclusive_stage(n)}
    return out


def topological(needs: Mapping[str, set[str]], order: Iterable[str] = ()) -> list[str]:
    """Sort stages upstream first; ties in ``order`` (DVC's order), then by name.  A cycle is a ValueError."""
    rank = {n: i for i, n in enumerate(order)}
    key = lambda n: (rank.get(n, len(rank)), n)  # noqa: E731
    left = {n: set(u) for n, u in needs.items()}
    out: list[str] = []
    while left:
        ready = sorted((n for n, u in left.items() if not u), key=key)
        if not ready:
            raise ValueError(f"the stage graph has a cycle among {sorted(left)}")
        for n in ready:
            out.append(n)
            del left[n]
        for u in left.values():
            u.difference_update(ready)
    return out


def remaining_path(needs: Mapping[str, set[str]], costs: Mapping[str, float] | None = None) -> dict[str, float]:
    """Compute per stage its cost (seconds last time, else 1) plus the longest chain of costs downstream of it."""
    costs = costs or {}
    children = _children(needs)
    path: dict[str, float] = {}
    for n in reversed(topological(needs)):
        path[n] = float(costs.get(n, 1.0)) + max((path[c] for c in children[n]), default=0.0)
    return path


def submission_order(needs: Mapping[str, set[str]], costs: Mapping[str, float] | None = None,
                     order: Iterable[str] = ()) -> list[str]:
    """Order the stages for submission: upstream first; among the ready ones the longest remaining path first.

    A stage's remaining path is its cost plus the longest chain of costs downstream of it (a critical-path
    priority); ties go by DVC's order, then by name.

    Parameters
    ----------
    needs : Mapping[str, set[str]]
        The stage graph.
    costs : Mapping[str, float], optional
        Seconds each stage took when it last ran; a stage without one costs 1.
    order : Iterable[str], optional
        DVC's order of the stages.

    Returns
    -------
    list[str]
        Every stage of ``needs``, each after its upstream stages.

    Raises
    ------
    ValueError
        The graph has a cycle.
    """
    path = remaining_path(needs, costs)
    rank = {n: i for i, n in enumerate(order)}
    left = {n: set(u) for n, u in needs.items()}
    out: list[str] = []
    while left:
        ready = [n for n, u in left.items() if not u]
        if not ready:
            raise ValueError(f"the stage graph has a cycle among {sorted(left)}")
        best = min(ready, key=lambda n: (-path[n], rank.get(n, len(rank)), n))
        out.append(best)
        del left[best]
        for u in left.values():
            u.discard(best)
    return out


def startable(sequence: Iterable[str], needs: Mapping[str, set[str]], finished: Iterable[str],
              running: Mapping[str, Mapping[str, float]], res: Mapping[str, Mapping[str, float]],
              capacity: Mapping[str, float]) -> list[str]:
    """Pick the stages to start now, in ``sequence``'s priority (:func:`submission_order`).

    A stage starts when it is not started, its upstream stages have finished, and its resources fit within
    ``capacity`` beside those ``running`` and those picked before it (a lower-priority stage that fits may pass
    one that does not); with nothing running, the first ready stage starts even when larger than the cluster.
    A stage is handed to Ray only once it may run, so a stage ready early (a ceiling needs only the data) does
    not hold the cores a critical-path stage needs next.

    Parameters
    ----------
    sequence : Iterable[str]
        The stages in priority order.
    needs : Mapping[str, set[str]]
        The stage graph.
    finished : Iterable[str]
        The stages that have finished, whatever their status.
    running : Mapping[str, Mapping[str, float]]
        The stages running now -> the resources they hold.
    res : Mapping[str, Mapping[str, float]]
        Each stage's resources (:func:`stage_resources`).
    capacity : Mapping[str, float]
        What the running stages may hold together (:attr:`Sizing.capacity`).

    Returns
    -------
    list[str]
        The stages to start, in priority order.
    """
    done, taken = set(finished), set(running)
    used = {k: sum(float(r.get(k, 0.0)) for r in running.values()) for k in capacity}
    out: list[str] = []
    for n in sequence:
        if n in done or n in taken or not set(needs.get(n, ())) <= done:
            continue
        if taken and any(used[k] + float(res[n].get(k, 0.0)) > float(capacity[k]) + 1e-9 for k in capacity):
            continue
        taken.add(n)
        used = {k: used[k] + float(res[n].get(k, 0.0)) for k in capacity}
        out.append(n)
    return out


@dataclasses.dataclass(frozen=True)
class Sizing:
    """What the cluster offers and what a stage may take (the rules: docs/scaling.md).

    Attributes
    ----------
    node_cpus : float
        The CPUs of the largest node: what an exclusive stage takes, and a stage's ceiling.
    gpus : float
        The cluster's GPUs; 0: every stage runs on the CPU.
    stage_cpus : float
        The CPUs a CPU stage takes (``geodistill run --stage-cpus``).
    train_gpu_fraction : float
        The share of a GPU one training run takes (``--train-gpu-fraction``).
    train_threads : int
        ``train.num_threads`` of the params; 0: not pinned.  A CPU training run takes at least this many CPUs.
    cluster_cpus : float
        All nodes' CPUs; 0: ``node_cpus``.
    """

    node_cpus: float
    gpus: float = 0.0
    stage_cpus: float = 1.0
    train_gpu_fraction: float = 0.25
    train_threads: int = 0
    cluster_cpus: float = 0.0

    @property
    def capacity(self) -> dict[str, float]:
        """What the running stages may hold together: ``{"num_cpus", "num_gpus"}``."""
        return {"num_cpus": float(self.cluster_cpus or self.node_cpus), "num_gpus": float(self.gpus)}


def stage_resources(name: str, size: Sizing) -> dict[str, float]:
    """Size one stage's Ray task (the rules: docs/scaling.md).

    With GPUs the teacher takes one whole GPU and a training run ``size.train_gpu_fraction`` of one, each with
    one CPU; an exclusive stage takes a whole node; any other stage ``size.stage_cpus`` CPUs (a training run at
    least ``size.train_threads``), at most a node's.

    Parameters
    ----------
    name : str
        The stage's name (``train_<method>@<seed>`` for a training run).
    size : Sizing
        What the cluster offers.

    Returns
    -------
    dict[str, float]
        ``{"num_cpus": ..., "num_gpus": ...}``.
    """
    base = name.split("@", 1)[0]
    if size.gpus > 0 and base == TEACHER_STAGE:
        return {"num_cpus": 1.0, "num_gpus": 1.0}
    if size.gpus > 0 and base.startswith(TRAIN_PREFIX):
        return {"num_cpus": 1.0, "num_gpus": float(size.train_gpu_fraction)}
    if exclusive_stage(name):
        return {"num_cpus": float(size.node_cpus), "num_gpus": 0.0}
    cpus = size.stage_cpus
    if base.startswith(TRAIN_PREFIX):
        cpus = max(cpus, float(size.train_threads))
    return {"num_cpus": float(min(cpus, size.node_cpus)), "num_gpus": 0.0}


def outcome(log_text: str) -> str:
    """Read from a successful ``dvc repro --single-item`` log what it did.

    Parameters
    ----------
    log_text : str
        The stage's stdout and stderr.

    Returns
    -------
    str
        ``"ran"``, ``"restored"`` (from DVC's run cache) or ``"up_to_date"``.
    """
    if "Running stage" in log_text:
        return "ran"
    if "is cached" in log_text:
        return "restored"
    return "up_to_date"


def error_line(log_text: str, limit: int = 300) -> str:
    """Find the line that says why a stage failed: the last error line, else the last line.

    An error line starts with ``ERROR`` or holds ``: error:`` or ``Error:``.

    Parameters
    ----------
    log_text : str
        The failed command's output.
    limit : int, optional
        The most characters kept.

    Returns
    -------
    str
        The line, stripped and cut to ``limit``; ``"(no output)"`` for an empty log.
    """
    lines = [ln.strip() for ln in log_text.splitlines() if ln.strip()]
    if not lines:
        return "(no output)"
    marked = [ln for ln in lines if ln.startswith("ERROR") or ": error:" in ln or "Error:" in ln]
    return (marked or lines)[-1][:limit]
