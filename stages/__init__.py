"""The DAG's stage scripts: read artifacts -> call pipeline -> write artifacts."""
