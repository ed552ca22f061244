"""Errors raised for bad data and bad generator settings (one line, naming the problem)."""


class DatasetError(ValueError):
    """A dataset on disk is missing, truncated, corrupted or inconsistent."""


class PlacementError(ValueError):
    """Objects cannot be placed without intersecting within the placement area."""


class OutputDirError(ValueError):
    """An output folder is not writable, or exists and is not empty."""
