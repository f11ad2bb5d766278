"""The human loop: rank, export to Label Studio / CVAT, import the corrections (``geodistill review``)."""
