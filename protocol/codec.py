"""msgpack codec of the wire contract.

A payload is one msgpack map::

    {"schema": "<MessageName>", "schema_version": <int>, <field>: <value>, ...}

Scalars travel as msgpack scalars, lists as arrays, nested records and string-keyed maps as maps,
``None`` as nil. A numpy array travels as a map ``{"dtype": "<f4", "shape": [N, 3], "data": bin}``
holding the raw little-endian bytes in C order.

:func:`decode` never raises anything but :class:`~protocol.errors.DecodeError`, whatever the
bytes: it caps the payload size, the msgpack container sizes and the nesting, whitelists array
dtypes, checks shapes against byte counts before touching the data, and finally runs the message's
own validation.
"""

from __future__ import annotations

import dataclasses
import functools
import math
from collections.abc import Mapping
from typing import Any, Final, TypeVar

import msgpack
import numpy as np

from protocol.errors import DecodeError, ValidationError
from protocol.messages import MESSAGE_TYPES, Detection, Message

MAX_PAYLOAD_BYTES: Final = 64 * 1024 * 1024
MAX_ARRAY_NDIM: Final = 4
_MAX_CONTAINER_LEN: Final = 100_000
_MAX_MAP_LEN: Final = 4_096
_ALLOWED_DTYPES: Final = frozenset(
    {"<f4", "<f8", "|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "|b1"}
)
_NESTED: Final[dict[tuple[str, str], type]] = {("RobotDetections", "detections"): Detection}
_REGISTRY: Final[dict[str, type[Message]]] = {cls.SCHEMA: cls for cls in MESSAGE_TYPES}

M = TypeVar("M", bound=Message)


# --------------------------------------------------------------------------------------------
# encode
# --------------------------------------------------------------------------------------------


def _array_to_wire(arr: np.ndarray) -> dict[str, Any]:
    le = arr.astype(arr.dtype.newbyteorder("<"), copy=False)
    return {
        "dtype": le.dtype.str,
        "shape": list(arr.shape),
        "data": np.ascontiguousarray(le).tobytes(),
    }


def _value_to_wire(value: Any) -> Any:
    if value is None or isinstance(value, (str, int, float)):
        return value
    if isinstance(value, np.ndarray):
        return _array_to_wire(value)
    if dataclasses.is_dataclass(value) and not isinstance(value, type):
        return {name: _value_to_wire(getattr(value, name)) for name in _field_names(type(value))}
    if isinstance(value, Mapping):
        return {str(k): _value_to_wire(v) for k, v in value.items()}
    if isinstance(value, (list, tuple)):
        return [_value_to_wire(v) for v in value]
    if isinstance(value, np.generic):
        return value.item()
    return value


@functools.cache
def _field_names(cls: type) -> tuple[str, ...]:
    return tuple(f.name for f in dataclasses.fields(cls))


def encode(msg: Message) -> bytes:
    """Serialize a message to its msgpack payload (see module docstring for the layout)."""
    if not isinstance(msg, Message) or type(msg).SCHEMA not in _REGISTRY:
        raise TypeError(f"not a protocol message: {type(msg).__name__}")
    body = _value_to_wire(msg)
    wire = {"schema": type(msg).SCHEMA, "schema_version": type(msg).VERSION, **body}
    return msgpack.packb(wire, use_bin_type=True)


# --------------------------------------------------------------------------------------------
# decode
# --------------------------------------------------------------------------------------------


def _array_from_wire(path: str, obj: Any) -> np.ndarray:
    if not isinstance(obj, dict) or set(obj) != {"dtype", "shape", "data"}:
        raise DecodeError(f"{path}: expected an array map with keys dtype, shape, data")
    dtype, shape, data = obj["dtype"], obj["shape"], obj["data"]
    if not isinstance(dtype, str) or dtype not in _ALLOWED_DTYPES:
        raise DecodeError(f"{path}: dtype {dtype!r} not allowed")
    if not isinstance(data, bytes):
        raise DecodeError(f"{path}: data must be binary, got {type(data).__name__}")
    if (
        not isinstance(shape, list)
        or len(shape) > MAX_ARRAY_NDIM
        or not all(isinstance(d, int) and not isinstance(d, bool) and d >= 0 for d in shape)
    ):
        raise DecodeError(f"{path}: shape must be a list of at most {MAX_ARRAY_NDIM} sizes >= 0")
    dt = np.dtype(dtype)
    count = math.prod(shape)
    if count * dt.itemsize != len(data):
        raise DecodeError(
            f"{path}: shape {shape} of {dtype} needs {count * dt.itemsize} bytes, got {len(data)}"
        )
    return np.frombuffer(data, dtype=dt).reshape(shape)


def _field_kind(f: dataclasses.Field) -> str:
    type_txt = str(f.type)
    if "ndarray" in type_txt:
        return "array"
    if type_txt.startswith("Mapping"):
        return "map"
    if type_txt.startswith("tuple"):
        return "tuple"
    return "scalar"


@functools.cache
def _field_specs(cls: type, schema: str) -> tuple[tuple[str, str, bool, type | None], ...]:
    """(name, kind, required, nested type) per field, computed once per class."""
    return tuple(
        (
            f.name,
            _field_kind(f),
            f.default is dataclasses.MISSING and f.default_factory is dataclasses.MISSING,
            _NESTED.get((schema, f.name)),
        )
        for f in dataclasses.fields(cls)
    )


def _record_from_wire(path: str, cls: type, obj: Any, schema: str) -> Any:
    if not isinstance(obj, dict):
        raise DecodeError(f"{path or cls.__name__}: expected a map, got {type(obj).__name__}")
    kwargs: dict[str, Any] = {}
    for name, kind, required, nested in _field_specs(cls, schema):
        if name not in obj:
            if required:
                raise DecodeError(
                    f"{path}.{name}: required field missing"
                    if path
                    else f"{name}: required field missing"
                )
            continue
        where = f"{path}.{name}" if path else name
        value = obj[name]
        if nested is not None:
            if not isinstance(value, list):
                raise DecodeError(f"{where}: expected a list, got {type(value).__name__}")
            value = tuple(
                _record_from_wire(f"{where}[{i}]", nested, item, nested.__name__)
                for i, item in enumerate(value)
            )
        elif kind == "array":
            value = None if value is None else _array_from_wire(where, value)
        elif kind == "map" and not isinstance(value, dict):
            raise DecodeError(f"{where}: expected a map, got {type(value).__name__}")
        elif kind == "tuple":
            if not isinstance(value, list):
                raise DecodeError(f"{where}: expected a list, got {type(value).__name__}")
            value = tuple(value)
        elif kind == "scalar" and isinstance(value, (dict, list, bytes)):
            raise DecodeError(f"{where}: expected a scalar, got {type(value).__name__}")
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except ValidationError as exc:
        field = f"{path}.{exc.field}" if path else exc.field
        raise DecodeError(f"{field}: {exc.reason}") from None


def decode(payload: bytes | bytearray | memoryview, expected: type[M] | None = None) -> M:
    """Parse and validate a payload; raise :class:`DecodeError` (only) when it is not valid.

    ``expected``: if given, the message must be of this type (e.g. a subscriber on a detections
    key accepts only :class:`~protocol.messages.RobotDetections`).
    """
    try:
        return _decode(payload, expected)
    except DecodeError:
        raise
    except Exception as exc:  # hostile bytes must never escape as anything else
        raise DecodeError(f"malformed payload: {type(exc).__name__}: {exc}"[:500]) from None


def _decode(payload: Any, expected: type[M] | None) -> M:
    if not isinstance(payload, (bytes, bytearray, memoryview)):
        raise DecodeError(f"payload must be bytes, got {type(payload).__name__}")
    if len(payload) > MAX_PAYLOAD_BYTES:
        raise DecodeError(f"payload of {len(payload)} bytes exceeds the {MAX_PAYLOAD_BYTES} limit")
    if len(payload) == 0:
        raise DecodeError("empty payload")
    try:
        obj = msgpack.unpackb(
            bytes(payload),
            raw=False,
            use_list=True,
            strict_map_key=True,
            max_str_len=MAX_PAYLOAD_BYTES,
            max_bin_len=MAX_PAYLOAD_BYTES,
            max_array_len=_MAX_CONTAINER_LEN,
            max_map_len=_MAX_MAP_LEN,
            max_ext_len=0,
        )
    except Exception as exc:
        raise DecodeError(f"not a msgpack document: {type(exc).__name__}: {exc}"[:300]) from None
    if not isinstance(obj, dict):
        raise DecodeError(f"top level must be a map, got {type(obj).__name__}")
    schema = obj.get("schema")
    if not isinstance(schema, str):
        raise DecodeError("missing or non-string 'schema'")
    cls = _REGISTRY.get(schema)
    if cls is None:
        raise DecodeError(f"unknown schema {schema[:64]!r}; known: {sorted(_REGISTRY)}")
    version = obj.get("schema_version")
    if not isinstance(version, int) or isinstance(version, bool):
        raise DecodeError(f"{schema}: missing or non-integer 'schema_version'")
    if version != cls.VERSION:
        raise DecodeError(
            f"{schema}: unsupported schema_version {version} (this build speaks {cls.VERSION})"
        )
    if expected is not None and cls is not expected:
        raise DecodeError(f"expected {expected.SCHEMA}, got {schema}")
    return _record_from_wire("", cls, obj, schema)
