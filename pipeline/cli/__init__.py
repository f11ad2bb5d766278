"""The user commands: the ``geodistill`` click group (:mod:`pipeline.cli.main`) and one module per tool
(label, distill, segment, review, run, dag and profile, plots, reproduce-check).  The DAG's stage
commands stay in ``stages/`` (``python -m stages.<name>``, dvc.yaml's cmds)."""
