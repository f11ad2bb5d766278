"""Past one machine: the DVC DAG on Ray (``geodistill run``).

* :mod:`pipeline.cluster.plan` -- pure: the stage graph from ``dvc dag --dot``, which stages to submit
  (``dvc status --json`` plus their downstream), the order (longest remaining path first), the exclusive
  stage (``benchmark``) placed after everything else, and each stage's Ray resources.
* :mod:`pipeline.cluster.guard` -- a stage's process group dies with the Ray worker that started it.
* :mod:`pipeline.cluster.driver` -- the one-driver lock, the DVC commands, the Ray tasks, the timeline.

DVC stays the record through its public commands only: every stage runs as
``dvc --wait-for-lock repro --single-item <stage>`` (the flag exists since DVC 3.61), so DVC decides
whether it is stale, restores it from its run cache or runs it, and writes its dvc.lock entry.  Ray is
imported lazily (the ``cluster`` extra).
"""
