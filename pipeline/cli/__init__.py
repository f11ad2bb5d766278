"""The user commands of the ``geodistill`` console script."""
