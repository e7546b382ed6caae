"""msgpack codec of the wire contract.

A payload is one msgpack map::

    {"schema": "<MessageName>", "schema_version": <int>, <field>: <value>, ...}

Scalars travel as msgpack scalars, lists as arrays, nested records and string-keyed maps as maps,
``None`` as nil. A numpy array travels as a map ``{"dtype": "<f4", "shape": [N, 3], "data": bin}``
holding the raw little-endian bytes in C order.

:func:`decode` never raises anything but :class:`~protocol.errors.DecodeError`, whatever the
bytes, and enforces every limit before it builds what the limit bounds (:mod:`protocol.limits`):
the payload cap (of the expected type before parsing, of the announced type right after reading
the envelope), the structure (each key and value of the top-level map is located by skipping
through the raw msgpack, never built), the unknown-key rule (checked on those raw spans), the
entry counts of lists and maps (read from their headers, so 10 000 nested detections cost nothing
before the 64-entry limit refuses them), the msgpack string, array and map sizes and the nesting;
then it whitelists array dtypes, checks shapes against byte counts before touching the data, and
finally runs the message's own validation.

Two paths give that guarantee. The native one (:func:`native_limits`) hands the whole payload to
msgpack's C unpacker with limits derived from the expected message type: no string, binary, list
or map longer than the largest valid message of that type holds anywhere, each refused from its
header, and no more containers than such a message has (counted by hooks as they are
finished); then the per-field entry counts and the unknown-key rule are checked on what was
built, before any message object is. It declines (returns nothing) on any limit, on unknown
keys and on anything unusual, and the careful path, which locates every key and value in the
raw bytes and builds nothing before its limit is checked, decides and names the limit. Both
give the same message or the same error; ``tests/protocol/test_codec_paths.py`` checks this on
fuzzed payloads.
"""

from __future__ import annotations

import dataclasses
import functools
import sys
from collections.abc import Mapping
from types import MappingProxyType
from typing import Any, Final, TypeVar

import msgpack
import numpy as np

from protocol.errors import DecodeError, ValidationError
from protocol.limits import (
    MAX_ARRAY_ENTRIES,
    MAX_MAP_ENTRIES,
    MAX_PAYLOAD_BYTES,
    MAX_STR_BYTES,
    MAX_UNKNOWN_KEYS,
    MAX_UNKNOWN_VALUE_BYTES,
    PAYLOAD_CAPS,
    LimitError,
    check_payload_size,
)
from protocol.messages import MAX_ENTRIES, MESSAGE_TYPES, Detection, Message

MAX_ARRAY_NDIM: Final = 4
_ALLOWED_DTYPES: Final = frozenset(
    {"<f4", "<f8", "|u1", "|i1", "<u2", "<i2", "<u4", "<i4", "<u8", "<i8", "|b1"}
)
_NESTED: Final[dict[tuple[str, str], type]] = {("RobotDetections", "detections"): Detection}
_REGISTRY: Final[dict[str, type[Message]]] = {cls.SCHEMA: cls for cls in MESSAGE_TYPES}
_ARRAY_KEYS: Final = frozenset({"dtype", "shape", "data"})
_LITTLE_ENDIAN_HOST: Final = sys.byteorder == "little"
#: the allowed wire dtypes, looked up once
_WIRE_DTYPES: Final[dict[str, np.dtype]] = {name: np.dtype(name) for name in _ALLOWED_DTYPES}

M = TypeVar("M", bound=Message)


# --------------------------------------------------------------------------------------------
# encode
# --------------------------------------------------------------------------------------------


def _array_to_wire(arr: np.ndarray) -> dict[str, Any]:
    dt = arr.dtype
    if dt.byteorder == ">" or (dt.byteorder == "=" and not _LITTLE_ENDIAN_HOST):
        arr = arr.astype(dt.newbyteorder("<"))
        dt = arr.dtype
    # tobytes() is C order whatever the array's layout
    return {"dtype": dt.str, "shape": list(arr.shape), "data": arr.tobytes()}


#: types sent as they are (bool and int subclasses by the general rule below)
_AS_IS: Final = frozenset({type(None), str, int, float, bool})


def _value_to_wire(value: Any) -> Any:
    kind = type(value)
    # the exact types of a message's fields first, each decided by one lookup
    if kind in _AS_IS:
        return value
    if kind is np.ndarray:
        return _array_to_wire(value)
    if kind is tuple or kind is list:
        return [_value_to_wire(v) for v in value]
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
    if not isinstance(obj, dict) or len(obj) != 3 or not _ARRAY_KEYS.issuperset(obj):
        raise DecodeError(f"{path}: expected an array map with keys dtype, shape, data")
    dtype, shape, data = obj["dtype"], obj["shape"], obj["data"]
    dt = _WIRE_DTYPES.get(dtype) if isinstance(dtype, str) else None
    if dt is None:
        raise DecodeError(f"{path}: dtype {dtype!r} not allowed")
    if not isinstance(data, bytes):
        raise DecodeError(f"{path}: data must be binary, got {type(data).__name__}")
    count = 1
    if isinstance(shape, list) and len(shape) <= MAX_ARRAY_NDIM:
        for d in shape:
            # exactly int (msgpack's integers; a bool is not a size)
            if type(d) is not int or d < 0:
                count = -1
                break
            count *= d
    else:
        count = -1
    if count < 0:
        raise DecodeError(f"{path}: shape must be a list of at most {MAX_ARRAY_NDIM} sizes >= 0")
    if count * dt.itemsize != len(data):
        raise DecodeError(
            f"{path}: shape {shape} of {dtype} needs {count * dt.itemsize} bytes, got {len(data)}"
        )
    # a view of the payload's bytes: read-only, C-contiguous, nothing copied
    return np.ndarray(shape, dt, data)


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


def _where(path: str, name: str) -> str:
    return f"{path}.{name}" if path else name


def _record_from_wire(path: str, cls: type, obj: Any, schema: str) -> Any:
    if not isinstance(obj, dict):
        raise DecodeError(f"{path or cls.__name__}: expected a map, got {type(obj).__name__}")
    kwargs: dict[str, Any] = {}
    # field paths are spelled only for an error message (this runs for every field received)
    for name, kind, required, nested in _field_specs(cls, schema):
        if name not in obj:
            if required:
                raise DecodeError(f"{_where(path, name)}: required field missing")
            continue
        value = obj[name]
        if kind == "scalar" and nested is None:
            if isinstance(value, (dict, list, bytes)):
                raise DecodeError(
                    f"{_where(path, name)}: expected a scalar, got {type(value).__name__}")
        elif nested is not None:
            if not isinstance(value, list):
                raise DecodeError(
                    f"{_where(path, name)}: expected a list, got {type(value).__name__}")
            where = _where(path, name)
            value = tuple([
                _record_from_wire(f"{where}[{i}]", nested, item, nested.__name__)
                for i, item in enumerate(value)
            ])
        elif kind == "array":
            if value is not None:
                value = _array_from_wire(_where(path, name), value)
        elif kind == "map":
            if not isinstance(value, dict):
                raise DecodeError(
                    f"{_where(path, name)}: expected a map, got {type(value).__name__}")
        elif kind == "tuple":
            if not isinstance(value, list):
                raise DecodeError(
                    f"{_where(path, name)}: expected a list, got {type(value).__name__}")
            value = tuple(value)
        kwargs[name] = value
    try:
        return cls(**kwargs)
    except ValidationError as exc:
        field = f"{path}.{exc.field}" if path else exc.field
        raise DecodeError(f"{field}: {exc.reason}") from None


def decode(payload: bytes | bytearray | memoryview, expected: type[M] | None = None) -> M:
    """Parse and validate a payload; raise :class:`DecodeError` (only) when it is not valid.

    ``expected``: if given, the message must be of this type (e.g. a subscriber on a detections
    key accepts only :class:`~protocol.messages.RobotDetections`), and its payload cap
    (:data:`protocol.limits.PAYLOAD_CAPS`) is checked before anything is parsed. A payload over
    a limit raises :class:`~protocol.limits.LimitError`, a :class:`DecodeError` naming the limit.
    """
    return _decode(payload, expected, native=True)


def decode_checked(payload: bytes | bytearray | memoryview,
                   expected: type[M] | None = None) -> M:
    """:func:`decode` by the careful path alone (no native fast path): the reference the fast
    path is tested against, and the peer of the fast paths in ``smartedge bench codec``."""
    return _decode(payload, expected, native=False)


def message_from_wire(obj: Mapping[str, Any]) -> Message:
    """The message of an already unpacked payload (a dict as ``msgpack.unpackb`` returns it),
    with the message's own validation but none of the codec's limits: for payloads from a
    trusted source, and the unbounded peer of ``smartedge bench codec``. Raises
    :class:`DecodeError`."""
    if not isinstance(obj, dict):
        raise DecodeError(f"expected a map, got {type(obj).__name__}")
    cls = _REGISTRY.get(obj.get("schema"))  # type: ignore[arg-type]
    if cls is None:
        raise DecodeError(f"unknown schema {str(obj.get('schema'))[:64]!r}")
    return _record_from_wire("", cls, obj, cls.SCHEMA)


def _decode(payload: Any, expected: type[M] | None, native: bool) -> M:
    """The payload cap, then the native path (if ``native``) and the careful one; any
    exception but :class:`DecodeError` becomes one (hostile bytes never escape otherwise)."""
    try:
        if not isinstance(payload, (bytes, bytearray, memoryview)):
            raise DecodeError(f"payload must be bytes, got {type(payload).__name__}")
        size = payload.nbytes if isinstance(payload, memoryview) else len(payload)
        check_payload_size(size, None if expected is None else expected.SCHEMA)
        buf = payload if isinstance(payload, bytes) else bytes(payload)
        if len(buf) == 0:
            raise DecodeError("empty payload")
        if native:
            fast = _decode_native(buf, expected)
            if fast is not None:
                return fast
        return _decode_checked(buf, expected)
    except DecodeError:
        raise
    except Exception as exc:
        raise DecodeError(f"malformed payload: {type(exc).__name__}: {exc}"[:500]) from None


def _decode_checked(buf: bytes, expected: type[M] | None) -> M:
    """The careful path: the raw structure located and checked before anything is built (every
    payload the native path declines, and the reference it is tested against)."""
    data = memoryview(buf)
    kind, _ = _container_header(data, 0)
    if kind != "map":
        raise DecodeError(f"top level must be a map, got {_wire_type(buf[0])}")
    try:
        unpacker = _unpacker(data)
        spans = _scan_map(unpacker, data, 0, "")
        trailing = len(buf) - unpacker.tell()
    except DecodeError:
        raise
    except Exception as exc:
        raise DecodeError(f"not a msgpack document: {type(exc).__name__}: {exc}"[:300]) from None
    del unpacker  # its copy of the payload
    if trailing:
        raise DecodeError(f"{trailing} trailing bytes after the message")
    schema = _scalar_at(data, spans.get("schema"))
    if not isinstance(schema, str):
        raise DecodeError("missing or non-string 'schema'")
    cls = _REGISTRY.get(schema)
    if cls is None:
        raise DecodeError(f"unknown schema {schema[:64]!r}; known: {sorted(_REGISTRY)}")
    version = _scalar_at(data, spans.get("schema_version"))
    if not isinstance(version, int) or isinstance(version, bool):
        raise DecodeError(f"{schema}: missing or non-integer 'schema_version'")
    if version != cls.VERSION:
        raise DecodeError(
            f"{schema}: unsupported schema_version {version} (this build speaks {cls.VERSION})"
        )
    if expected is not None and cls is not expected:
        raise DecodeError(f"expected {expected.SCHEMA}, got {schema}")
    check_payload_size(len(buf), schema)
    _check_unknown_keys(spans, _known_keys(cls) | _ENVELOPE, "")
    return _record_from_wire(
        "", cls, _build_known(data, spans, cls, schema, "", (0, len(buf))), schema)


# --------------------------------------------------------------------------------------------
# the native path: msgpack's own limits, derived per message type
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class NativeLimits:
    """What the largest valid message of a type holds, as msgpack's C unpacker enforces it while
    it reads headers: no string, binary, list or map longer than the type allows anywhere
    (``unpack``), and no more containers than its largest valid message has
    (``max_containers``, counted by the hooks as each container is finished)."""

    unpack: Mapping[str, int]
    max_containers: int


def _record_shape(cls: type, schema: str) -> tuple[int, int, int]:
    """(longest list, largest map, containers) of the largest valid record of ``cls``: array
    maps with their shape lists, list and map fields at their entry limits, nested records at
    their count limit, and every record map with room for its unknown keys."""
    longest_list, largest_map = MAX_ARRAY_NDIM, 3  # an array map: dtype, shape, data
    containers = 1
    for name, kind, _required, nested in _field_specs(cls, schema):
        limit = MAX_ENTRIES.get((schema, name))
        if nested is not None:
            count = MAX_ARRAY_ENTRIES if limit is None else limit
            n_list, n_map, n_containers = _record_shape(nested, nested.__name__)
            longest_list = max(longest_list, count, n_list)
            largest_map = max(largest_map, n_map)
            containers += 1 + count * n_containers
        elif kind == "array":
            containers += 2
        elif kind == "tuple":
            longest_list = max(longest_list, MAX_ARRAY_ENTRIES if limit is None else limit)
            containers += 1
        elif kind == "map":
            largest_map = max(largest_map, MAX_MAP_ENTRIES if limit is None else limit)
            containers += 1
    fields = len(_field_specs(cls, schema)) + len(_ENVELOPE) + MAX_UNKNOWN_KEYS
    return longest_list, max(largest_map, fields), containers


@functools.cache
def native_limits(cls: type[Message] | None) -> NativeLimits:
    """The native limits of one message type (``None``: of the loosest type, for a payload whose
    type is not known before it is read). Never looser than the structural limits of
    :mod:`protocol.limits`."""
    if cls is None:
        each = [native_limits(c) for c in MESSAGE_TYPES]
        unpack = {k: max(n.unpack[k] for n in each) for k in each[0].unpack}
        return NativeLimits(MappingProxyType(unpack), max(n.max_containers for n in each))
    longest_list, largest_map, containers = _record_shape(cls, cls.SCHEMA)
    unpack = {
        "max_str_len": MAX_STR_BYTES,
        "max_bin_len": min(MAX_PAYLOAD_BYTES, PAYLOAD_CAPS.get(cls.SCHEMA, MAX_PAYLOAD_BYTES)),
        "max_array_len": min(MAX_ARRAY_ENTRIES, longest_list),
        "max_map_len": min(MAX_MAP_ENTRIES, largest_map),
        "max_ext_len": 0,
    }
    return NativeLimits(MappingProxyType(unpack), containers)


class _TooManyContainers(Exception):
    pass


def _decode_native(buf: bytes, expected: type[M] | None) -> M | None:
    """The common case in one native pass: ``msgpack.unpackb`` under :func:`native_limits`, then
    the exact per-field counts on what was built, then the message's own validation. ``None``
    whenever the payload is anything but a plain valid message of a known type with only known
    keys (any limit hit, unknown keys, a wrong envelope, trailing bytes): the careful path then
    decides, and names the exact limit or field. A :class:`DecodeError` from the message's own
    validation is final: the careful path would build the same values and get the same one."""
    limits = native_limits(expected)
    left = [limits.max_containers]

    def on_map(finished: dict[Any, Any]) -> dict[Any, Any]:
        # object_hook, not object_pairs_hook: the same count at the same moment (each map
        # as it is finished), without a list of pairs built and copied into a dict
        left[0] -= 1
        if left[0] < 0:
            raise _TooManyContainers
        return finished

    def on_list(items: list[Any]) -> list[Any]:
        left[0] -= 1
        if left[0] < 0:
            raise _TooManyContainers
        return items

    try:
        obj = msgpack.unpackb(buf, raw=False, use_list=True, strict_map_key=True,
                              object_hook=on_map, list_hook=on_list, **limits.unpack)
    except Exception:
        return None
    if not isinstance(obj, dict):
        return None
    schema = obj.get("schema")
    cls = _REGISTRY.get(schema) if isinstance(schema, str) else None
    version = obj.get("schema_version")
    if (cls is None or (expected is not None and cls is not expected)
            or type(version) is not int or version != cls.VERSION
            or len(buf) > PAYLOAD_CAPS.get(schema, MAX_PAYLOAD_BYTES)
            or not _only_known(obj, cls, schema)):
        return None
    return _record_from_wire("", cls, obj, schema)


@functools.cache
def _entry_rules(cls: type, schema: str, top: bool) -> tuple[frozenset[str],
                                                             tuple[tuple[str, int], ...],
                                                             tuple[tuple[str, type], ...]]:
    """(known keys, with the envelope for a top-level record; (field, entry limit) pairs;
    (field, nested type) pairs)."""
    specs = _field_specs(cls, schema)
    limits = tuple((name, MAX_ENTRIES[(schema, name)]) for name, *_ in specs
                   if (schema, name) in MAX_ENTRIES)
    nested = tuple((name, n) for name, _k, _r, n in specs if n is not None)
    return _known_keys(cls) | (_ENVELOPE if top else frozenset()), limits, nested


def _only_known(obj: Mapping[Any, Any], cls: type, schema: str, top: bool = True) -> bool:
    """No unknown key in the record (nor in its nested records, where the envelope keys are
    unknown too) and every list and map field within its entry limit."""
    known, limits, nested = _entry_rules(cls, schema, top)
    if not known.issuperset(obj):
        return False
    for name, limit in limits:
        value = obj.get(name)
        if isinstance(value, (list, dict)) and len(value) > limit:
            return False
    for name, ncls in nested:
        value = obj.get(name)
        if isinstance(value, list):
            for item in value:
                if isinstance(item, dict) and not _only_known(item, ncls, ncls.__name__, False):
                    return False
    return True


# --------------------------------------------------------------------------------------------
# the raw msgpack structure, read before anything large is built
# --------------------------------------------------------------------------------------------

_ENVELOPE: Final = frozenset({"schema", "schema_version"})
#: longest packed key of a record (a str8 of 253 bytes): field names are short identifiers
_MAX_KEY_BYTES: Final = 255
_UNPACK_LIMITS: Final[dict[str, int]] = {
    "max_str_len": MAX_STR_BYTES,
    "max_bin_len": MAX_PAYLOAD_BYTES,
    "max_array_len": MAX_ARRAY_ENTRIES,
    "max_map_len": MAX_MAP_ENTRIES,
    "max_ext_len": 0,
}
Span = tuple[int, int]


def _unpacker(data: memoryview) -> msgpack.Unpacker:
    unpacker = msgpack.Unpacker(
        raw=False, use_list=True, strict_map_key=True, max_buffer_size=max(1, len(data)),
        **_UNPACK_LIMITS,
    )
    unpacker.feed(data)
    return unpacker


def _unpack(data: memoryview) -> Any:
    """One complete msgpack object (the slice of a value), under the receiver's limits."""
    return msgpack.unpackb(data, raw=False, use_list=True, strict_map_key=True, **_UNPACK_LIMITS)


def _wire_type(first: int) -> str:
    if first <= 0x7F or first >= 0xE0 or 0xCC <= first <= 0xD3:
        return "int"
    if 0x90 <= first <= 0x9F or first in (0xDC, 0xDD):
        return "list"
    if 0xA0 <= first <= 0xBF or 0xD9 <= first <= 0xDB:
        return "str"
    if 0xC4 <= first <= 0xC6:
        return "bytes"
    if first in (0xCA, 0xCB):
        return "float"
    if first in (0xC2, 0xC3):
        return "bool"
    if first == 0xC0:
        return "NoneType"
    return f"msgpack type 0x{first:02x}"


#: byte width of the entry count after a list16/list32/map16/map32 header byte
_HEADER_WIDTH: Final = {0xDC: 2, 0xDD: 4, 0xDE: 2, 0xDF: 4}


def _container_header(data: memoryview, pos: int) -> tuple[str, int]:
    """(``"map"``/``"list"``/``""``, number of entries) of the msgpack object at ``pos``, read
    from its header alone."""
    if pos >= len(data):
        return "", 0
    first = data[pos]
    if 0x80 <= first <= 0x8F:
        return "map", first & 0x0F
    if 0x90 <= first <= 0x9F:
        return "list", first & 0x0F
    width = _HEADER_WIDTH.get(first)
    if width is None or pos + 1 + width > len(data):
        return "", 0
    count = int.from_bytes(data[pos + 1 : pos + 1 + width], "big")
    return ("list" if first in (0xDC, 0xDD) else "map"), count


def _scan_map(
    unpacker: msgpack.Unpacker, data: memoryview, base: int, path: str
) -> dict[str, Span]:
    """The spans (offsets in ``data``) of the values of the map at the unpacker's position, by
    key; values are skipped, not built. ``base``: offset in ``data`` of the unpacker's input."""
    count = unpacker.read_map_header()
    if count > MAX_MAP_ENTRIES:
        raise LimitError("too_many_entries",
                         f"{path or 'message'}: map of {count} entries (limit {MAX_MAP_ENTRIES})")
    spans: dict[str, Span] = {}
    for _ in range(count):
        k0 = unpacker.tell()
        unpacker.skip()
        k1 = unpacker.tell()
        if k1 - k0 > _MAX_KEY_BYTES:
            raise LimitError("unknown_key_too_large",
                             f"{path or 'message'}: a key of {k1 - k0} bytes "
                             f"(limit {_MAX_KEY_BYTES})")
        first = data[base + k0]
        if 0xA0 <= first <= 0xBF:  # a fixstr, as every field name is: no unpacker needed
            key: Any = bytes(data[base + k0 + 1 : base + k1]).decode("utf-8")
        else:
            key = _unpack(data[base + k0 : base + k1])
        if not isinstance(key, str):
            raise DecodeError(f"{path or 'message'}: map keys must be strings, "
                              f"got {type(key).__name__}")
        v0 = unpacker.tell()
        unpacker.skip()
        spans[key] = (base + v0, base + unpacker.tell())
    return spans


def _check_unknown_keys(spans: Mapping[str, Span], known: frozenset[str], path: str) -> None:
    """The unknown-key rule: at most :data:`MAX_UNKNOWN_KEYS` unknown keys per record, each
    value at most :data:`MAX_UNKNOWN_VALUE_BYTES` packed."""
    unknown = [(k, end - start) for k, (start, end) in spans.items() if k not in known]
    where = path or "message"
    if len(unknown) > MAX_UNKNOWN_KEYS:
        raise LimitError("too_many_unknown_keys",
                         f"{where}: {len(unknown)} unknown keys (limit {MAX_UNKNOWN_KEYS})")
    for key, size in unknown:
        if size > MAX_UNKNOWN_VALUE_BYTES:
            raise LimitError("unknown_key_too_large",
                             f"{where}: unknown key {key[:64]!r} holds {size} bytes "
                             f"(limit {MAX_UNKNOWN_VALUE_BYTES})")


def _scalar_at(data: memoryview, span: Span | None) -> Any:
    """The value at ``span`` if it is a scalar (never builds a container), else ``None``."""
    if span is None or _container_header(data, span[0])[0]:
        return None
    return _unpack(data[span[0] : span[1]])


@functools.cache
def _known_keys(cls: type) -> frozenset[str]:
    return frozenset(_field_names(cls))


def _build_known(
    data: memoryview, spans: Mapping[str, Span], cls: type, schema: str, path: str,
    record: Span | None = None,
) -> dict[str, Any]:
    """The known fields of a record as plain msgpack values; containers have their entry counts
    checked from their headers first, nested records are scanned the same way. ``record``: the
    record's own span; when given and the record holds no nested records, it is unpacked in one
    go once the checks passed (its unknown keys are already bounded in number and size)."""
    specs = _field_specs(cls, schema)
    whole = record is not None and not _has_nested(cls, schema)
    obj: dict[str, Any] = {}
    for name, _kind, _required, nested in specs:
        span = spans.get(name)
        if span is None:
            continue
        limit = MAX_ENTRIES.get((schema, name))
        if limit is not None or nested is not None:
            kind, count = _container_header(data, span[0])
            if limit is not None and kind and count > limit:
                where = f"{path}.{name}" if path else name
                raise LimitError("too_many_entries", f"{where}: {count} entries (limit {limit})")
            if nested is not None and kind == "list":
                where = f"{path}.{name}" if path else name
                obj[name] = _build_nested(data, span, nested, where)
                continue
        if not whole:
            obj[name] = _unpack(data[span[0] : span[1]])
    if whole:
        assert record is not None
        full = _unpack(data[record[0] : record[1]])
        return {name: full[name] for name, *_ in specs if name in full}
    return obj


@functools.cache
def _has_nested(cls: type, schema: str) -> bool:
    return any(nested is not None for *_, nested in _field_specs(cls, schema))


def _build_nested(data: memoryview, span: Span, cls: type, path: str) -> list[Any]:
    """A list of nested records (its length already checked): each record's known fields, its
    unknown keys size-checked and never built."""
    unpacker = _unpacker(data[span[0] : span[1]])
    items: list[Any] = []
    for i in range(unpacker.read_array_header()):
        where = f"{path}[{i}]"
        start = span[0] + unpacker.tell()
        if _container_header(data, start)[0] != "map":
            unpacker.skip()
            items.append(_unpack(data[start : span[0] + unpacker.tell()]))
            continue
        spans = _scan_map(unpacker, data, span[0], where)
        _check_unknown_keys(spans, _known_keys(cls), where)
        record = (start, span[0] + unpacker.tell())
        items.append(_build_known(data, spans, cls, cls.__name__, where, record))
    return items
