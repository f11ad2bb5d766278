"""The pipeline composed: the DVC DAG, the prepare stage, and the standalone distill lane."""
