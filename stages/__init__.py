"""Stage commands: thin click wrappers (read artifacts -> call pipeline -> write artifacts)."""
