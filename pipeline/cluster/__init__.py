"""Past one machine: the DVC DAG on Ray (``geodistill run``; docs/scaling.md)."""
