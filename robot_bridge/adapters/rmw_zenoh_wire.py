"""rmw_zenoh's wire conventions as pure functions: what a ROS 2 node on rmw_zenoh (Jazzy and
newer) puts on Zenoh, so the bridge can be such a node without a bridge process.

* topic keys ``<domain_id>/<topic>/<DDS type>/<RIHS01 type hash>`` (:func:`topic_key`,
  :func:`dds_type_name`, :func:`type_hash` from rosbags' Jazzy typestore);
* the 33-byte sample attachment (sequence number, source timestamp in ns since the Unix epoch,
  16-byte GID) and the 77-byte keyed layout of rmw_zenoh_cpp < 0.2.4
  (:func:`encode_attachment`, :func:`encode_keyed_attachment`, :func:`decode_attachment`);
* liveliness tokens ``@ros2_lv/...`` with mangled names (:func:`liveliness_token_key`,
  :func:`parse_liveliness_token`);
* the QoS field of a token and how a publisher's QoS maps onto Zenoh (:func:`qos_to_keyexpr`,
  :func:`qos_from_keyexpr`, :func:`adapt_qos`, :func:`zenoh_publication_mode`).

The payload is CDR as for DDS (:mod:`robot_bridge.adapters.ros2`'s codecs). Every fact, with
the upstream file it comes from, is in docs/robot_bridge.md, "ROS 2 on rmw_zenoh", "What goes
over the wire". Upstream sources (``ros2/rmw_zenoh``, branches ``jazzy``/``rolling``):
``docs/design.md``; in ``rmw_zenoh_cpp/src/detail/``: ``liveliness_utils.cpp`` (``TopicInfo``,
``Entity``, ``qos_to_keyexpr``, ``keyexpr_to_qos``), ``attachment_helpers.cpp``, ``qos.cpp``
(``best_available_qos``), ``type_support_common.cpp``, ``rmw_publisher_data.cpp``,
``rmw_subscription_data.cpp``; ``rmw/types.h`` for the QoS enum values; ``zenoh-cpp``'s
``include/zenoh/api/ext/serialization.hxx`` for the attachment's serializer.

Nothing here opens or uses a Zenoh session; :mod:`robot_bridge.adapters.rmw_zenoh` does.
"""

from __future__ import annotations

import dataclasses
import enum
import functools
import re
import struct
from typing import Any, Final

from robot_bridge.adapters.ros2 import RosConversionError

#: prefix of every rmw_zenoh liveliness token (a Zenoh hermetic chunk)
ADMIN_SPACE: Final = "@ros2_lv"
#: entity kinds in a liveliness token: node, message publisher / subscription, service server /
#: client
NODE: Final = "NN"
PUBLISHER: Final = "MP"
SUBSCRIPTION: Final = "MS"
SERVICE: Final = "SS"
CLIENT: Final = "SC"
ENTITY_KINDS: Final = (NODE, PUBLISHER, SUBSCRIPTION, SERVICE, CLIENT)
#: what replaces "/" in a token's fields
SLASH_REPLACEMENT: Final = "%"
#: bytes of a GID on the wire (RMW_GID_STORAGE_SIZE since Jazzy)
GID_SIZE: Final = 16
#: bytes of the attachment (two int64, the GID's length byte, the GID)
ATTACHMENT_SIZE: Final = 8 + 8 + 1 + GID_SIZE
#: attachment layouts: ``compact`` (rmw_zenoh_cpp >= 0.2.4) and ``keyed`` (Jazzy 0.2.0 to 0.2.3)
ATTACHMENT_FORMATS: Final = ("compact", "keyed")

_KEYED_FIELDS: Final = (b"sequence_number", b"source_timestamp", b"source_gid")
_INT64: Final = struct.Struct("<q")
_NAME_TOKEN: Final = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_TYPE_TOKEN: Final = re.compile(r"[A-Za-z][A-Za-z0-9_]*")
#: the chunk characters Zenoh reserves (wildcards, verbatim, DSL)
_KEY_RESERVED: Final = re.compile(r"[*$?#\s]")


class AttachmentError(RosConversionError):
    """Bytes that are not an rmw_zenoh attachment (the reason says why)."""


# --------------------------------------------------------------------------------------------
# QoS (rmw/types.h enum values, rmw_zenoh's defaults and its token encoding)
# --------------------------------------------------------------------------------------------


class Reliability(enum.IntEnum):
    """``rmw_qos_reliability_policy_e`` values (``rmw/types.h``)."""

    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class Durability(enum.IntEnum):
    """``rmw_qos_durability_policy_e`` values (``rmw/types.h``)."""

    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class History(enum.IntEnum):
    """``rmw_qos_history_policy_e`` values (``rmw/types.h``)."""

    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2
    UNKNOWN = 3


class Liveliness(enum.IntEnum):
    """``rmw_qos_liveliness_policy_e`` values (``rmw/types.h``)."""

    SYSTEM_DEFAULT = 0
    AUTOMATIC = 1
    MANUAL_BY_TOPIC = 3
    UNKNOWN = 4
    BEST_AVAILABLE = 5


#: RMW_DURATION_INFINITE as (sec, nsec)
DURATION_INFINITE: Final = (9_223_372_036, 854_775_807)
#: the depth rmw_zenoh picks for depth 0 (qos.cpp)
DEFAULT_DEPTH: Final = 42


@dataclasses.dataclass(frozen=True)
class QosProfile:
    """The ROS QoS fields rmw_zenoh encodes in a liveliness token. Durations are
    ``(sec, nsec)``; the defaults are rmw_zenoh's (``qos.cpp``), which the token leaves out."""

    reliability: int = Reliability.RELIABLE
    durability: int = Durability.VOLATILE
    history: int = History.KEEP_LAST
    depth: int = DEFAULT_DEPTH
    deadline: tuple[int, int] = DURATION_INFINITE
    lifespan: tuple[int, int] = DURATION_INFINITE
    liveliness: int = Liveliness.AUTOMATIC
    liveliness_lease_duration: tuple[int, int] = DURATION_INFINITE


#: rmw_zenoh's default profile (what "system default" becomes)
RMW_ZENOH_DEFAULT_QOS: Final = QosProfile()


def adapt_qos(qos: QosProfile) -> QosProfile:
    """``qos`` with system defaults (and ``UNKNOWN``) replaced by rmw_zenoh's defaults and depth
    0 by 42, as rmw_zenoh's ``best_available_qos`` does before writing a token."""
    d = RMW_ZENOH_DEFAULT_QOS
    unset_r = (Reliability.SYSTEM_DEFAULT, Reliability.UNKNOWN)
    unset_d = (Durability.SYSTEM_DEFAULT, Durability.UNKNOWN)
    unset_h = (History.SYSTEM_DEFAULT, History.UNKNOWN)
    unset_l = (Liveliness.SYSTEM_DEFAULT, Liveliness.UNKNOWN)

    def duration(value: tuple[int, int], default: tuple[int, int]) -> tuple[int, int]:
        sec, nsec = value
        return default if (sec, nsec) == (0, 0) else (int(sec), int(nsec))  # unspecified

    return dataclasses.replace(
        qos,
        reliability=d.reliability if qos.reliability in unset_r else qos.reliability,
        durability=d.durability if qos.durability in unset_d else qos.durability,
        history=d.history if qos.history in unset_h else qos.history,
        depth=d.depth if qos.depth == 0 else qos.depth,
        deadline=duration(qos.deadline, d.deadline),
        lifespan=duration(qos.lifespan, d.lifespan),
        liveliness=d.liveliness if qos.liveliness in unset_l else qos.liveliness,
        liveliness_lease_duration=duration(qos.liveliness_lease_duration,
                                           d.liveliness_lease_duration),
    )


def qos_to_keyexpr(qos: QosProfile) -> str:
    """The token's QoS field (``qos_to_keyexpr`` of rmw_zenoh): ``R:D:H,depth:DLs,DLns:LSs,LSns:
    LV,LVs,LVns`` with every value equal to rmw_zenoh's default left empty. rclcpp's default
    ``QoS(10)`` gives ``::,10:,:,:,,``. Pass an adapted profile (:func:`adapt_qos`)."""
    d = RMW_ZENOH_DEFAULT_QOS

    def field(value: int, default: int) -> str:
        return "" if int(value) == int(default) else str(int(value))

    return ":".join((
        field(qos.reliability, d.reliability),
        field(qos.durability, d.durability),
        f"{field(qos.history, d.history)},{field(qos.depth, d.depth)}",
        f"{field(qos.deadline[0], d.deadline[0])},{field(qos.deadline[1], d.deadline[1])}",
        f"{field(qos.lifespan[0], d.lifespan[0])},{field(qos.lifespan[1], d.lifespan[1])}",
        ",".join((
            field(qos.liveliness, d.liveliness),
            field(qos.liveliness_lease_duration[0], d.liveliness_lease_duration[0]),
            field(qos.liveliness_lease_duration[1], d.liveliness_lease_duration[1]),
        )),
    ))


def qos_from_keyexpr(text: str) -> QosProfile:
    """Parse a token's QoS field (rmw_zenoh's ``keyexpr_to_qos``): empty values are the
    defaults. ``ValueError`` on anything rmw_zenoh would reject."""
    parts = text.split(":")
    if len(parts) < 6:
        raise ValueError(f"QoS {text!r}: expected 6 ':'-separated fields")
    history, deadline, lifespan = (parts[i].split(",") for i in (2, 3, 4))
    liveliness = parts[5].split(",")
    if len(history) < 2 or len(deadline) < 2 or len(lifespan) < 2 or len(liveliness) < 3:
        raise ValueError(f"QoS {text!r}: missing ','-separated values")
    d = RMW_ZENOH_DEFAULT_QOS

    def number(value: str, default: int, enum_type: type[enum.IntEnum] | None = None) -> int:
        if value == "":
            return int(default)
        if not value.isdigit():
            raise ValueError(f"QoS {text!r}: {value!r} is not a number")
        if enum_type is not None and int(value) not in enum_type._value2member_map_:
            raise ValueError(f"QoS {text!r}: {value!r} is not a {enum_type.__name__} value")
        return int(value)

    return QosProfile(
        reliability=number(parts[0], d.reliability, Reliability),
        durability=number(parts[1], d.durability, Durability),
        history=number(history[0], d.history, History),
        depth=number(history[1], d.depth),
        deadline=(number(deadline[0], d.deadline[0]), number(deadline[1], d.deadline[1])),
        lifespan=(number(lifespan[0], d.lifespan[0]), number(lifespan[1], d.lifespan[1])),
        liveliness=number(liveliness[0], d.liveliness, Liveliness),
        liveliness_lease_duration=(number(liveliness[1], d.liveliness_lease_duration[0]),
                                   number(liveliness[2], d.liveliness_lease_duration[1])),
    )


def zenoh_publication_mode(qos: QosProfile) -> tuple[bool, bool]:
    """``(reliable, block)``: how rmw_zenoh declares the Zenoh publisher of a ROS publisher
    with (adapted) ``qos``: reliable for RELIABLE, congestion control BLOCK only for RELIABLE
    with KEEP_ALL, DROP otherwise (``rmw_publisher_data.cpp``)."""
    reliable = qos.reliability == Reliability.RELIABLE
    return reliable, reliable and qos.history == History.KEEP_ALL


# --------------------------------------------------------------------------------------------
# names, types, keys
# --------------------------------------------------------------------------------------------


def mangle_name(name: str) -> str:
    """A token field: every ``/`` replaced by ``%`` (``/robot1`` → ``%robot1``, ``/`` → ``%``)."""
    return name.replace("/", SLASH_REPLACEMENT)


def demangle_name(name: str) -> str:
    """The inverse of :func:`mangle_name`."""
    return name.replace(SLASH_REPLACEMENT, "/")


def _name_tokens(name: str, what: str) -> list[str]:
    tokens = [t for t in name.split("/") if t]
    if "//" in name.strip("/") or any(not _NAME_TOKEN.fullmatch(t) for t in tokens):
        raise ValueError(
            f"invalid ROS {what} {name!r}: tokens of letters, digits and '_', "
            "not starting with a digit ('~' and substitutions are not supported)")
    return tokens


def is_node_name(name: str) -> bool:
    """Whether ``name`` is a valid ROS node name (letters, digits, ``_``; no leading digit)."""
    return _NAME_TOKEN.fullmatch(str(name)) is not None


def node_namespace(namespace: str) -> str:
    """A ROS namespace in its absolute form: ``""``/``"/"`` → ``/``, ``robot1/`` → ``/robot1``.
    ``ValueError`` for a name ROS would reject."""
    tokens = _name_tokens(str(namespace).strip(), "namespace")
    return "/" + "/".join(tokens)


def fully_qualified_name(topic: str, namespace: str = "") -> str:
    """ROS name resolution for the bridge's node in ``namespace``: a relative ``topic``
    (``odom``) is put in the namespace (``/robot1/odom``), an absolute one (``/odom``) is kept.
    ``ValueError`` for an empty or invalid name."""
    name = str(topic).strip()
    tokens = _name_tokens(name, "topic name")
    if not tokens or name.endswith("/"):
        raise ValueError(f"invalid ROS topic name {topic!r}")
    if name.startswith("/"):
        return "/" + "/".join(tokens)
    ns = node_namespace(namespace)
    return ("" if ns == "/" else ns) + "/" + "/".join(tokens)


def dds_type_name(ros_type: str) -> str:
    """The DDS type name rmw_zenoh puts in keys: ``geometry_msgs/msg/PoseStamped`` →
    ``geometry_msgs::msg::dds_::PoseStamped_``. ``ValueError`` for a malformed type."""
    parts = str(ros_type).split("/")
    if len(parts) != 3 or not all(_TYPE_TOKEN.fullmatch(p) for p in parts):
        raise ValueError(f"invalid ROS type {ros_type!r}: expected '<package>/msg/<Name>'")
    package, kind, name = parts
    return f"{package}::{kind}::dds_::{name}_"


@functools.cache
def _hash_store() -> Any:
    from rosbags.typesys import Stores, get_typestore

    # the message definitions of the distro rmw_zenoh targets; the hash is over them
    store = getattr(Stores, "ROS2_JAZZY", None) or Stores.LATEST
    return get_typestore(store)


@functools.cache
def type_hash(ros_type: str) -> str:
    """REP-2016 type hash ``RIHS01_<64 hex>`` of ``ros_type`` from its message definition
    (rosbags' Jazzy typestore); ``ValueError`` for a type the store does not know."""
    try:
        value = str(_hash_store().hash_rihs01(ros_type))
    except Exception as exc:  # rosbags raises KeyError / TypesysError for unknown types
        raise ValueError(f"no type hash for {ros_type!r}: {type(exc).__name__}: {exc}") from None
    if not re.fullmatch(r"RIHS01_[0-9a-f]{64}", value):
        raise ValueError(f"unexpected type hash {value!r} for {ros_type!r}")
    return value


def check_domain_id(domain_id: int) -> int:
    """``domain_id`` when it is an integer >= 0 (the first chunk of every key), else
    ``ValueError``."""
    if isinstance(domain_id, bool) or not isinstance(domain_id, int) or domain_id < 0:
        raise ValueError(f"ROS domain id {domain_id!r}: expected an integer >= 0")
    return domain_id


def topic_key(domain_id: int, topic: str, ros_type: str, type_hash_: str | None = None) -> str:
    """The Zenoh key of a ROS 2 topic under rmw_zenoh: ``<domain_id>/<topic>/<dds type>/<hash>``
    with the fully qualified ``topic``'s outer slashes stripped, e.g.
    ``0/chatter/std_msgs::msg::dds_::String_/RIHS01_df66…``. ``type_hash_`` defaults to
    :func:`type_hash` of ``ros_type``."""
    name = "/".join(_name_tokens(str(topic).strip(), "topic name"))
    if not name:
        raise ValueError(f"invalid ROS topic name {topic!r}")
    digest = type_hash(ros_type) if type_hash_ is None else type_hash_
    return f"{check_domain_id(domain_id)}/{name}/{dds_type_name(ros_type)}/{digest}"


def liveliness_token_key(
    domain_id: int, zid: str, node_id: int, entity_id: int, kind: str, *,
    node_name: str, namespace: str = "/", enclave: str = "/",
    topic: str | None = None, ros_type: str | None = None, type_hash_: str | None = None,
    qos: QosProfile | None = None,
) -> str:
    """The liveliness token of an rmw_zenoh entity (``liveliness_utils.cpp``):

    ``@ros2_lv/<domain>/<zid>/<node_id>/<entity_id>/<kind>/<enclave>/<namespace>/<node_name>``
    followed, for a publisher (``MP``), subscription (``MS``), service or client, by
    ``/<topic>/<dds type>/<type hash>/<qos>``. A node (``NN``) uses its ``node_id`` as
    ``entity_id``. ``namespace`` and ``enclave`` are absolute (``/`` for none), ``topic`` fully
    qualified (``/robot1/odom``); all are mangled (``/`` → ``%``). ``qos`` is adapted
    (:func:`adapt_qos`) and encoded with :func:`qos_to_keyexpr` (rmw_zenoh's default when
    ``None``)."""
    if kind not in ENTITY_KINDS:
        raise ValueError(f"entity kind {kind!r}: expected one of {ENTITY_KINDS}")
    if not re.fullmatch(r"[0-9a-f]+", str(zid)):
        raise ValueError(f"zenoh id {zid!r}: expected lowercase hex")
    if not is_node_name(node_name):
        raise ValueError(f"invalid ROS node name {node_name!r}")
    for value, what in ((node_id, "node id"), (entity_id, "entity id")):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{what} {value!r}: expected an integer >= 0")
    if kind == NODE and entity_id != node_id:
        raise ValueError("a node's token carries its node id twice")
    enclave_abs = "/" if str(enclave).strip() in ("", "/") else "/" + str(enclave).strip("/")
    parts = [ADMIN_SPACE, str(check_domain_id(domain_id)), str(zid), str(node_id),
             str(entity_id), kind, mangle_name(enclave_abs),
             mangle_name(node_namespace(namespace)), str(node_name)]
    if kind != NODE:
        if topic is None or ros_type is None:
            raise ValueError(f"a {kind} token needs a topic and a type")
        fqn = "/" + "/".join(_name_tokens(str(topic).strip(), "topic name"))
        if fqn == "/":
            raise ValueError(f"invalid ROS topic name {topic!r}")
        digest = type_hash(ros_type) if type_hash_ is None else type_hash_
        parts += [mangle_name(fqn), dds_type_name(ros_type), mangle_name(digest),
                  qos_to_keyexpr(adapt_qos(qos or RMW_ZENOH_DEFAULT_QOS))]
    key = "/".join(parts)
    if _KEY_RESERVED.search(key):
        raise ValueError(f"liveliness key {key!r} has a character Zenoh reserves")
    return key


@dataclasses.dataclass(frozen=True)
class EntityToken:
    """A parsed liveliness token (see :func:`parse_liveliness_token`). Names are demangled;
    ``topic``, ``ros_type`` (DDS spelling), ``type_hash`` and ``qos`` are ``None`` for a node."""

    domain_id: int
    zid: str
    node_id: str
    entity_id: str
    kind: str
    enclave: str
    namespace: str
    node_name: str
    topic: str | None = None
    ros_type: str | None = None
    type_hash: str | None = None
    qos: QosProfile | None = None


def parse_liveliness_token(key: str) -> EntityToken:
    """Read a liveliness token as rmw_zenoh's graph cache does (``Entity::make``): at least 9
    non-empty chunks (13 for a topic entity), the ``@ros2_lv`` admin space, a known kind, a
    numeric domain and a valid QoS field. ``ValueError`` otherwise."""
    parts = str(key).split("/")
    if len(parts) < 9 or any(p == "" for p in parts):
        raise ValueError(f"liveliness token {key!r}: expected >= 9 non-empty chunks")
    if parts[0] != ADMIN_SPACE or parts[5] not in ENTITY_KINDS or not parts[1].isdigit():
        raise ValueError(f"liveliness token {key!r}: not an rmw_zenoh entity")
    node = EntityToken(domain_id=int(parts[1]), zid=parts[2], node_id=parts[3],
                       entity_id=parts[4], kind=parts[5], enclave=demangle_name(parts[6]),
                       namespace=demangle_name(parts[7]), node_name=demangle_name(parts[8]))
    if node.kind == NODE:
        return node
    if len(parts) < 13:
        raise ValueError(f"liveliness token {key!r}: a {node.kind} token has 13 chunks")
    return dataclasses.replace(
        node, topic=demangle_name(parts[9]), ros_type=demangle_name(parts[10]),
        type_hash=demangle_name(parts[11]), qos=qos_from_keyexpr(parts[12]))


# --------------------------------------------------------------------------------------------
# attachment
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass(frozen=True)
class Attachment:
    """What rmw_zenoh attaches to every sample: the publisher's sequence number (from 1), the
    source timestamp (ns since the Unix epoch) and the publisher's 16-byte GID."""

    sequence_number: int
    source_timestamp_ns: int
    source_gid: bytes


def _int64(value: int, what: str) -> bytes:
    if isinstance(value, bool) or not isinstance(value, int) or not -(2**63) <= value < 2**63:
        raise ValueError(f"{what} {value!r} does not fit an int64")
    return _INT64.pack(value)


def _check_gid(gid: bytes) -> bytes:
    gid = bytes(gid)
    if len(gid) != GID_SIZE:
        raise ValueError(f"GID of {len(gid)} bytes: rmw_zenoh's are {GID_SIZE}")
    return gid


def _zenoh_ext_str(text: bytes) -> bytes:
    # zenoh-ext string: LEB128 length (one byte below 128), then the UTF-8 bytes
    return bytes([len(text)]) + text


def encode_attachment(seq: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The 33-byte rmw_zenoh attachment: ``seq`` and ``source_timestamp_ns`` as little-endian
    int64, then ``0x10`` (the GID's length) and the 16 ``gid`` bytes. ``ValueError`` when a
    value does not fit."""
    gid = _check_gid(gid)
    return (_int64(seq, "sequence number") + _int64(source_timestamp_ns, "source timestamp")
            + bytes([GID_SIZE]) + gid)


def encode_keyed_attachment(seq: int, source_timestamp_ns: int, gid: bytes) -> bytes:
    """The attachment of rmw_zenoh_cpp < 0.2.4 (Jazzy, before Apr 2025): each value after its
    name as a zenoh-ext string (77 bytes)."""
    gid = _check_gid(gid)
    k_seq, k_ts, k_gid = (_zenoh_ext_str(k) for k in _KEYED_FIELDS)
    return (k_seq + _int64(seq, "sequence number") + k_ts
            + _int64(source_timestamp_ns, "source timestamp") + k_gid + bytes([GID_SIZE]) + gid)


class _Reader:
    """Sequential zenoh-ext deserializer over bytes; :class:`AttachmentError` when short."""

    def __init__(self, data: bytes) -> None:
        self.data = data
        self.pos = 0

    def take(self, n: int, what: str) -> bytes:
        if self.pos + n > len(self.data):
            raise AttachmentError(f"attachment ends inside the {what}")
        out = self.data[self.pos:self.pos + n]
        self.pos += n
        return out

    def int64(self, what: str) -> int:
        return int(_INT64.unpack(self.take(8, what))[0])

    def length(self, what: str) -> int:
        value, shift = 0, 0
        while True:  # LEB128, as zenoh-ext writes sequence and string lengths
            byte = self.take(1, f"length of the {what}")[0]
            value |= (byte & 0x7F) << shift
            if byte < 0x80:
                return value
            shift += 7
            if shift > 63:
                raise AttachmentError(f"length of the {what} overflows")

    def key(self, expected: bytes) -> None:
        name = self.take(self.length("field name"), "field name")
        if name != expected:
            raise AttachmentError(f"expected field {expected.decode()!r}, got {name!r}")


def decode_attachment(data: Any) -> Attachment:
    """Read an rmw_zenoh attachment the way ``AttachmentData(const zenoh::Bytes &)`` does:
    int64, int64, then a sequence of exactly 16 bytes (trailing bytes are ignored, as there).
    The keyed layout of rmw_zenoh_cpp < 0.2.4 is recognised by its first field name.
    :class:`AttachmentError` for anything else."""
    if not isinstance(data, (bytes, bytearray, memoryview)):
        raise AttachmentError(f"attachment is {type(data).__name__}, not bytes")
    reader = _Reader(bytes(data))
    keyed = reader.data.startswith(_zenoh_ext_str(_KEYED_FIELDS[0]))
    if keyed:
        reader.key(_KEYED_FIELDS[0])
    seq = reader.int64("sequence number")
    if keyed:
        reader.key(_KEYED_FIELDS[1])
    stamp = reader.int64("source timestamp")
    if keyed:
        reader.key(_KEYED_FIELDS[2])
    n = reader.length("source GID")
    if n != GID_SIZE:
        raise AttachmentError(f"source GID of {n} bytes, expected {GID_SIZE}")
    return Attachment(seq, stamp, reader.take(GID_SIZE, "source GID"))
