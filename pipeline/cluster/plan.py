"""What ``geodistill run`` submits, in which order, with which Ray resources: pure functions of the outputs of
``dvc dag --dot`` and ``dvc status --json``.
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
    """``dvc dag --dot`` -> (stages in DVC's order, {stage: its upstream stages}), ``.dvc`` file nodes dropped."""
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
    children: dict[str, set[str]] = {n: set() for n in needs}
    for n, ups in needs.items():
        for u in ups:
            children[u].add(n)
    return children


def _reach(edges: Mapping[str, Iterable[str]], roots: Iterable[str]) -> set[str]:
    seen, todo = set(), list(roots)
    while todo:
        n = todo.pop()
        if n not in seen:
            seen.add(n)
            todo.extend(edges.get(n, ()))
    return seen


def downstream(needs: Mapping[str, set[str]], roots: Iterable[str]) -> set[str]:
    """``roots`` and every stage that depends on one of them, directly or not."""
    return _reach(_children(needs), [r for r in roots if r in needs])


def upstream(needs: Mapping[str, set[str]], roots: Iterable[str]) -> set[str]:
    """``roots`` and every stage they depend on, directly or not."""
    return _reach(needs, roots)


def to_submit(needs: Mapping[str, set[str]], stale: Iterable[str], targets: Iterable[str] = ()) -> set[str]:
    """The stale stages and everything downstream of them (DVC decides at each one's turn), within
    ``targets`` and their upstream stages when given.
    """
    chosen = downstream(needs, stale)
    targets = list(targets)
    return chosen & upstream(needs, targets) if targets else chosen


def subgraph(needs: Mapping[str, set[str]], keep: set[str]) -> dict[str, set[str]]:
    """``needs`` restricted to ``keep``: a kept stage waits for every kept stage upstream of it."""
    return {n: upstream(needs, needs[n]) & keep for n in keep}


def exclusive_stage(name: str) -> bool:
    """True for a stage that measures wall time (the catalogue's ``exclusive``)."""
    spec = STAGES.get(name.split("@", 1)[0])
    return bool(spec and spec.exclusive)


def run_alone(needs: Mapping[str, set[str]]) -> dict[str, set[str]]:
    """Exclusive stages after every stage that does not depend on them, so nothing runs beside them."""
    out = {n: set(u) for n, u in needs.items()}
    for x in (n for n in needs if exclusive_stage(n)):
        after = downstream(needs, [x])
        out[x] |= {n for n in needs if n not in after and not exclusive_stage(n)}
    return out


def topological(needs: Mapping[str, set[str]], order: Iterable[str] = ()) -> list[str]:
    """Stages upstream first; ties in ``order`` (DVC's order), then by name.  A cycle is an error."""
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
    """Per stage: its cost (seconds last time, else 1) plus the longest chain of costs downstream of it."""
    costs = costs or {}
    children = _children(needs)
    path: dict[str, float] = {}
    for n in reversed(topological(needs)):
        path[n] = float(costs.get(n, 1.0)) + max((path[c] for c in children[n]), default=0.0)
    return path


def submission_order(needs: Mapping[str, set[str]], costs: Mapping[str, float] | None = None,
                     order: Iterable[str] = ()) -> list[str]:
    """Upstream stages first; among the ready ones the longest remaining path first, then DVC's order."""
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
    """The stages to start now, in ``sequence``'s priority (:func:`submission_order`): each not started, its
    upstream finished, and its resources (``res``) within ``capacity`` beside those ``running`` and those picked
    before it (a lower-priority stage that fits may pass one that does not); with nothing running, the first
    ready stage starts even when larger than the cluster.  A stage is handed to Ray only once it may run, so a
    stage ready early (a ceiling needs only the data) does not hold the cores a critical-path stage needs next.
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
    """What the cluster offers and what a stage may take (``train_threads``: train.num_threads, 0 = not pinned;
    ``cluster_cpus``: all nodes' CPUs, 0 = ``node_cpus``).
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
    """Ray resources of one stage's task, ``{"num_cpus", "num_gpus"}`` (the rules: docs/scaling.md)."""
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
    """What ``dvc repro --single-item`` did: ``ran`` | ``restored`` (run cache) | ``up_to_date``."""
    if "Running stage" in log_text:
        return "ran"
    if "is cached" in log_text:
        return "restored"
    return "up_to_date"


def error_line(log_text: str, limit: int = 300) -> str:
    """The line that says why a stage failed: the last ``ERROR``/``error:`` line, else the last line."""
    lines = [ln.strip() for ln in log_text.splitlines() if ln.strip()]
    if not lines:
        return "(no output)"
    marked = [ln for ln in lines if ln.startswith("ERROR") or ": error:" in ln or "Error:" in ln]
    return (marked or lines)[-1][:limit]
