"""Field checks shared by the message dataclasses.

Each checker returns the normalised value or raises :class:`ValidationError` naming the field.
Arrays are returned as read-only, C-contiguous, native-endian copies so a frozen message really
is immutable.
"""

from __future__ import annotations

import functools
import math
import re
from collections.abc import Mapping, Sequence
from typing import Any, Final

import numpy as np

from protocol.errors import ValidationError

MAX_ID_LEN: Final = 64
MAX_TEXT_LEN: Final = 4096
INT64_MAX: Final = 2**63 - 1
_ID_RE: Final = re.compile(r"^[A-Za-z0-9_.\-]+$")


def check_id(field: str, value: Any, *, allow_empty: bool = False) -> str:
    """An identifier usable as one chunk of a Zenoh key expression: ``[A-Za-z0-9_.-]{1,64}``."""
    if not isinstance(value, str):
        raise ValidationError(field, f"expected a string id, got {type(value).__name__}")
    if value == "" and allow_empty:
        return value
    if not value or len(value) > MAX_ID_LEN or not _ID_RE.match(value):
        raise ValidationError(
            field, f"invalid id {value[:80]!r}: use 1-{MAX_ID_LEN} chars of [A-Za-z0-9_.-]"
        )
    return value


def check_text(field: str, value: Any, *, max_len: int = MAX_TEXT_LEN) -> str:
    if not isinstance(value, str):
        raise ValidationError(field, f"expected a string, got {type(value).__name__}")
    if len(value) > max_len:
        raise ValidationError(field, f"string longer than {max_len} characters")
    return value


def check_choice(field: str, value: Any, choices: Sequence[str]) -> str:
    if not isinstance(value, str) or value not in choices:
        raise ValidationError(field, f"expected one of {list(choices)}, got {value!r}")
    return value


def check_int(field: str, value: Any, *, lo: int = 0, hi: int = INT64_MAX) -> int:
    if type(value) is int and lo <= value <= hi:  # the common case, decided at once
        return value
    if isinstance(value, bool) or not isinstance(value, (int, np.integer)):
        raise ValidationError(field, f"expected an integer, got {type(value).__name__}")
    value = int(value)
    if not lo <= value <= hi:
        raise ValidationError(field, f"{value} outside [{lo}, {hi}]")
    return value


def check_float(
    field: str,
    value: Any,
    *,
    lo: float = -math.inf,
    hi: float = math.inf,
    finite: bool = True,
) -> float:
    if type(value) is float and lo <= value <= hi and (value - value == 0.0 or not finite):
        return value  # the common case: a finite float in range (x - x is NaN for inf/NaN)
    if isinstance(value, bool) or not isinstance(value, (int, float, np.integer, np.floating)):
        raise ValidationError(field, f"expected a number, got {type(value).__name__}")
    value = float(value)
    if math.isnan(value):
        if finite:
            raise ValidationError(field, "NaN is not allowed")
        return value
    if finite and math.isinf(value):
        raise ValidationError(field, "infinity is not allowed")
    if not lo <= value <= hi:
        raise ValidationError(field, f"{value} outside [{lo}, {hi}]")
    return value


@functools.cache
def _allowed_dtypes(dtypes: tuple[str, ...]) -> frozenset[np.dtype]:
    return frozenset(np.dtype(d) for d in dtypes)


def check_array(
    field: str,
    value: Any,
    *,
    dtypes: Sequence[str],
    shape: Sequence[int | None],
    finite: bool = True,
    max_elems: int | None = None,
) -> np.ndarray:
    """Check an array's dtype (one of ``dtypes``, numpy names) and shape (``None`` = any size).

    Lists are accepted and converted to the first allowed dtype. The returned array is
    read-only, native-endian and C-contiguous: the input itself when it already is all of
    that and read-only (e.g. decoded from a payload), otherwise a copy, so a frozen message
    never shares writeable memory with its creator.
    """
    if isinstance(value, np.ndarray):
        arr = value
        if arr.dtype not in _allowed_dtypes(tuple(dtypes)) and (
            arr.dtype.newbyteorder("=") not in _allowed_dtypes(tuple(dtypes))
        ):
            raise ValidationError(
                field, f"dtype {arr.dtype.name} not allowed; expected one of {list(dtypes)}"
            )
    elif isinstance(value, (list, tuple)):
        try:
            arr = np.asarray(value, dtype=dtypes[0])
        except (TypeError, ValueError, OverflowError) as exc:
            raise ValidationError(field, f"cannot convert to {dtypes[0]} array: {exc}") from exc
        if arr.size == 0:
            arr = arr.reshape([0 if d is None else d for d in shape] if None in shape else shape)
    else:
        raise ValidationError(field, f"expected an array, got {type(value).__name__}")
    got_shape = arr.shape
    if len(got_shape) != len(shape):
        _shape_mismatch(field, got_shape, shape)
    for got, want in zip(got_shape, shape):  # noqa: B905 - lengths compared just above
        if want is not None and got != want:
            _shape_mismatch(field, got_shape, shape)
    if max_elems is not None and arr.size > max_elems:
        raise ValidationError(field, f"{arr.size} elements exceed the limit of {max_elems}")
    if finite and arr.dtype.kind == "f" and not _all_finite(arr):
        raise ValidationError(field, "NaN or infinity is not allowed")
    flags = arr.flags
    if not flags.writeable and flags.c_contiguous and arr.dtype.isnative:
        return arr
    out = np.array(arr, dtype=arr.dtype.newbyteorder("="), order="C", copy=True)
    out.setflags(write=False)
    return out


def _shape_mismatch(field: str, got: tuple[int, ...], shape: Sequence[int | None]) -> None:
    want_txt = "x".join("N" if d is None else str(d) for d in shape)
    raise ValidationError(field, f"shape {got} does not match ({want_txt})")


def _all_finite(arr: np.ndarray) -> bool:
    """Every element of a float array finite. The sum of squares is finite exactly when every
    element is, unless a finite one is so large that it overflows: only then is each element
    looked at (the common small array costs one BLAS dot instead of a temporary and a
    reduction)."""
    if math.isfinite(np.vdot(arr, arr)):
        return True
    return bool(np.isfinite(arr).all())


def check_covariance(field: str, value: Any, dim: int = 3) -> np.ndarray:
    """A ``dim x dim`` float64 covariance: finite, symmetric, non-negative diagonal."""
    cov = check_array(field, value, dtypes=("float64", "float32"), shape=(dim, dim))
    cov = cov.astype(np.float64)
    magnitude = np.abs(cov)
    scale = max(1.0, float(magnitude.max()))
    # np.allclose(cov, cov.T, rtol=1e-6, atol=1e-9 * scale) written out (cov is finite here):
    # every pose and odometry message passes this, and allclose's generality costs 4x as much
    if not (np.abs(cov - cov.T) <= 1e-9 * scale + 1e-6 * magnitude.T).all():
        raise ValidationError(field, "covariance is not symmetric")
    if np.any(np.diag(cov) < 0.0):
        raise ValidationError(field, "covariance has a negative variance on its diagonal")
    cov.setflags(write=False)
    return cov


def check_str_tuple(field: str, value: Any, *, max_items: int = 256, ids: bool = True) -> tuple:
    if isinstance(value, str) or not isinstance(value, (list, tuple)):
        raise ValidationError(field, f"expected a list of strings, got {type(value).__name__}")
    if len(value) > max_items:
        raise ValidationError(field, f"more than {max_items} items")
    check = check_id if ids else check_text
    return tuple(check(f"{field}[{i}]", v) for i, v in enumerate(value))


def check_number_map(
    field: str, value: Any, *, integer: bool = False, max_items: int = 256
) -> Mapping[str, float | int]:
    if not isinstance(value, Mapping):
        raise ValidationError(field, f"expected a map, got {type(value).__name__}")
    if len(value) > max_items:
        raise ValidationError(field, f"more than {max_items} entries")
    out: dict[str, float | int] = {}
    for key, val in value.items():
        name = check_text(f"{field} key", key, max_len=128)
        if integer:
            out[name] = check_int(f"{field}[{name!r}]", val)
        else:
            out[name] = check_float(f"{field}[{name!r}]", val, finite=False)
    return out
