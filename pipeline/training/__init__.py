"""Training: the loop, its inputs read from artifacts, resume state, streaming, budgets, the supervised ceiling."""
