"""Developer tools outside the library, run from the checkout as ``python -m tools.<name>`` (never imported by it)."""
