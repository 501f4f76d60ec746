"""Errors raised by the dataset loaders and generators."""


class DatasetError(Exception):
    """A dataset could not be read; the message names the file (and line) at fault."""
