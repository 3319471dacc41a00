"""Exceptions with messages meant for users (no traceback needed)."""


class PointGNError(Exception):
    """Base class: an error the user can act on; the message says what and where."""


class BankError(PointGNError):
    """A feature bank file is missing, corrupt, or does not match the encoder."""


class DatasetError(PointGNError):
    """A dataset path or file cannot be read; the message names the file."""


class DecodeError(PointGNError):
    """A PointCloud2 message cannot be decoded; the message says why."""
