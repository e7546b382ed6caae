"""Exceptions of the wire contract.

Everything raised on purpose by :mod:`protocol` derives from :class:`ProtocolError`, so a service
can catch one type at its boundary. :class:`DecodeError` is the only exception
:func:`protocol.decode` lets escape, whatever the input bytes.
"""

from __future__ import annotations


class ProtocolError(Exception):
    """Base class of every error raised on purpose by the ``protocol`` package."""


class ValidationError(ProtocolError, ValueError):
    """A message field has the wrong type, shape, range or value.

    ``field`` names the offending field (dotted path for nested fields, e.g.
    ``detections[0].keypoints_px``).
    """

    def __init__(self, field: str, reason: str) -> None:
        super().__init__(f"{field}: {reason}")
        self.field = field
        self.reason = reason


class DecodeError(ProtocolError):
    """A payload could not be turned into a valid message; ``reason`` says why."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class ConfigFileError(ProtocolError):
    """A configuration file is missing, unreadable or invalid.

    The message always names the file and the key (dotted path) that is wrong.
    """

    def __init__(self, path: str, key: str, reason: str) -> None:
        where = f"{path}: {key}" if key else path
        super().__init__(f"{where}: {reason}")
        self.path = path
        self.key = key
        self.reason = reason


class SiteConfigError(ConfigFileError):
    """A site file (or a camera calibration file) is missing, unreadable or invalid."""
