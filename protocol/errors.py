"""Exceptions of the project.

:class:`SmartedgeError` is the one root of every user-facing error the project raises on purpose
(bad input, bad configuration, bad files): a command reports those as bad input; anything else is
a programming error and surfaces with its traceback. Everything raised on purpose by
:mod:`protocol` derives from :class:`ProtocolError`. :class:`DecodeError` is the only exception
:func:`protocol.decode` lets escape, whatever the input bytes.
"""

from __future__ import annotations


class SmartedgeError(Exception):
    """Root of every user-facing error of the project (configuration, input, files)."""


class ProtocolError(SmartedgeError):
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


class UsageError(SmartedgeError, ValueError):
    """A command-line option or a combination of options is wrong (the message says which)."""


class UnknownIdError(SmartedgeError, KeyError):
    """An id (camera, robot, source, adapter) is not known; the message lists the known ones."""

    def __str__(self) -> str:  # KeyError would print the message quoted
        return str(self.args[0]) if self.args else ""
