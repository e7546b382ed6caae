"""Reading YAML configuration files with errors that name the file and the dotted key.

:func:`read_yaml_file` reads and parses one (the only ``yaml.safe_load`` of the project's config
files: site files, scenarios, keypoint files); :class:`ConfigReader` holds the checks every
config parser here shares (site files, camera calibration files, simulation scenarios): each
raises the reader's error type (a :class:`~protocol.errors.ConfigFileError`) carrying the file
path, the key such as ``cameras[2].K`` and the reason.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from protocol.errors import ConfigFileError, SiteConfigError, ValidationError
from protocol.validation import check_id


def read_yaml_file(path: str | Path, what: str,
                   error: type[ConfigFileError] = SiteConfigError) -> Any:
    """The parsed YAML document of ``path`` (``what`` names the kind of file in messages, e.g.
    ``"site file"``); raises ``error(path, "", reason)`` when the file cannot be read, is not
    UTF-8 text or is not valid YAML. Checking the document is the caller's
    (:class:`ConfigReader`)."""
    p = Path(path)
    try:
        text = p.read_text(encoding="utf-8")
    except OSError as exc:
        raise error(str(p), "", f"cannot read {what}: {exc.strerror or exc}") from None
    except UnicodeDecodeError as exc:
        raise error(str(p), "", f"cannot read {what}: not UTF-8 text ({exc.reason})") from None
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        raise error(str(p), "", f"not valid YAML: {exc}") from None


def join_key(key: str, name: str) -> str:
    """``key.name``, or ``name`` at the top level."""
    return f"{key}.{name}" if key else name


class ConfigReader:
    """Typed access to a parsed YAML document; ``error`` is the exception type raised."""

    def __init__(self, path: str, error: type[ConfigFileError] = SiteConfigError) -> None:
        self.path = path
        self.error = error

    def fail(self, key: str, reason: str) -> ConfigFileError:
        return self.error(self.path, key, reason)

    def mapping(self, key: str, value: Any) -> Mapping[str, Any]:
        if not isinstance(value, Mapping):
            raise self.fail(key, f"expected a mapping, got {type(value).__name__}")
        return value

    def require(self, key: str, node: Mapping[str, Any], name: str) -> Any:
        if name not in node:
            raise self.fail(join_key(key, name), "required key is missing")
        return node[name]

    def no_unknown(self, key: str, node: Mapping[str, Any], allowed: set[str]) -> None:
        for name in node:
            if name not in allowed:
                raise self.fail(
                    join_key(key, str(name)), f"unknown key; allowed: {sorted(allowed)}"
                )

    def number(self, key: str, value: Any, lo: float = -math.inf, hi: float = math.inf) -> float:
        if isinstance(value, bool) or not isinstance(value, (int, float)):
            raise self.fail(key, f"expected a number, got {value!r}")
        if not math.isfinite(value) or not lo <= value <= hi:
            raise self.fail(key, f"{value} outside [{lo}, {hi}]")
        return float(value)

    def integer(self, key: str, value: Any, lo: int = 0, hi: int = 2**62) -> int:
        if isinstance(value, bool) or not isinstance(value, int):
            raise self.fail(key, f"expected an integer, got {value!r}")
        if not lo <= value <= hi:
            raise self.fail(key, f"{value} outside [{lo}, {hi}]")
        return value

    def ident(self, key: str, value: Any) -> str:
        try:
            return check_id(key, value)
        except ValidationError as exc:
            raise self.fail(key, exc.reason) from None

    def vector(self, key: str, value: Any, n: int) -> np.ndarray:
        """A list of exactly ``n`` finite numbers."""
        if not isinstance(value, list) or len(value) != n:
            raise self.fail(key, f"expected a list of {n} numbers")
        return np.array([self.number(f"{key}[{i}]", v) for i, v in enumerate(value)])

    def matrix(self, key: str, value: Any, rows: int | None, cols: int | None) -> np.ndarray:
        """A ``rows x cols`` matrix (nested or flat list), or a flat list when ``cols`` is None."""
        try:
            arr = np.asarray(value, dtype=np.float64)
        except (TypeError, ValueError):
            raise self.fail(key, "expected a list of numbers (or list of rows)") from None
        if arr.ndim == 1 and rows is not None and cols is not None and arr.size == rows * cols:
            arr = arr.reshape(rows, cols)
        if cols is None:
            if arr.ndim != 1:
                raise self.fail(key, f"expected a flat list, got shape {arr.shape}")
        elif arr.shape != (rows, cols):
            raise self.fail(key, f"expected a {rows}x{cols} matrix, got shape {arr.shape}")
        if not np.all(np.isfinite(arr)):
            raise self.fail(key, "contains NaN or infinity")
        return arr

    def section(self, key: str, value: Any, cls: type, *, int_lo: int = 0,
                fields: set[str] | None = None, base: Any = None) -> Any:
        """A flat dataclass with defaults from a mapping (``thresholds``, ``fusion``, ...).

        Unknown keys are errors; a field takes the type of its default: integers (>=
        ``int_lo``), booleans, strings, otherwise non-negative numbers (a ``None`` default
        takes a number). ``fields``: only these fields may be set (a section shared by
        several dataclasses); ``base``: an instance to start from instead of the defaults.
        The dataclass's own checks (``__post_init__``) are reported with the file and key.
        """
        node = self.mapping(key, value if value is not None else {})
        all_fields = {f.name: f for f in dataclasses.fields(cls)}
        allowed = set(all_fields) if fields is None else set(fields) & set(all_fields)
        kwargs = self.section_values(key, node, cls, allowed, int_lo=int_lo, strict=True)
        try:
            return dataclasses.replace(base, **kwargs) if base is not None else cls(**kwargs)
        except (TypeError, ValueError) as exc:
            raise self.fail(key, str(exc)) from None

    def section_values(self, key: str, node: Mapping[str, Any], cls: type, allowed: set[str],
                       *, int_lo: int = 0, strict: bool = False) -> dict[str, Any]:
        """The typed values of ``node``'s keys that are fields of ``cls`` in ``allowed``
        (``strict``: any other key is an error)."""
        fields = {f.name: f for f in dataclasses.fields(cls)}
        if strict:
            self.no_unknown(key, node, allowed)
        kwargs: dict[str, Any] = {}
        for name, val in node.items():
            if name not in allowed or name not in fields:
                continue
            f = fields[name]
            default = f.default
            if default is dataclasses.MISSING and f.default_factory is not dataclasses.MISSING:
                default = f.default_factory()
            k = join_key(key, name)
            if isinstance(default, bool):
                if not isinstance(val, bool):
                    raise self.fail(k, f"expected true or false, got {val!r}")
                kwargs[name] = val
            elif isinstance(default, int):
                kwargs[name] = self.integer(k, val, lo=int_lo)
            elif isinstance(default, str):
                if not isinstance(val, str):
                    raise self.fail(k, f"expected a string, got {val!r}")
                kwargs[name] = val
            else:
                kwargs[name] = self.number(k, val, lo=0.0)
        return kwargs
