"""ROS 2 robots on rmw_zenoh (Jazzy and newer), reached directly: no bridge process.

With ``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` every ROS 2 node is a Zenoh session, so the bridge
talks to the robot's nodes by speaking rmw_zenoh's conventions on its own Zenoh session. The
facts below were established from the rmw_zenoh sources (``ros2/rmw_zenoh``, branches
``jazzy``/``rolling``); the file each comes from is named.

**Topic key expression** (``docs/design.md`` "Topic and Service name mapping";
``rmw_zenoh_cpp/src/detail/liveliness_utils.cpp`` ``TopicInfo``)::

    <domain_id>/<fully qualified topic name, outer '/' stripped>/<type name>/<type hash>
    0/robot1/chatter/std_msgs::msg::dds_::String_/RIHS01_df668c74...6b1a18

The name's inner ``/`` stay (they are Zenoh chunk separators). The type name is the DDS one,
``<pkg>::msg::dds_::<Name>_`` (``type_support_common.cpp`` ``_create_type_name``). The type
hash is REP-2016's ``RIHS01_<sha256 hex>`` of the type description (``rosidl_stringify_type_hash``
in ``rmw_publisher_data.cpp``); rosbags computes the same (``hash_rihs01``; the Jazzy store is
used, and its hashes equal the ones the design document and Jazzy's ``ros2 topic info -v``
print). Humble's rmw_zenoh has no type hashes and cannot talk to Jazzy (README, "Known issues").

**Payload** (``docs/design.md`` "Serialization"; ``type_support.cpp``, ``cdr.cpp``): CDR as for
DDS, with the 4-byte encapsulation header (``serialize_encapsulation``, ``DDS_CDR``, host endian:
little endian ``00 01 00 00`` on every Tier-1 platform). No Zenoh encoding is set. rosbags'
``serialize_cdr`` writes exactly this, so :mod:`robot_bridge.adapters.ros2`'s codecs are reused.

**Attachment** (``docs/design.md`` "Publishers"; ``attachment_helpers.cpp``; the zenoh-ext
serializer of ``zenoh-cpp`` ``include/zenoh/api/ext/serialization.hxx``). Every sample carries::

    int64 sequence_number   8 bytes little endian, 1 for a publisher's first message
    int64 source_timestamp  8 bytes little endian, ns since the Unix epoch (system clock)
    uint8[16] source_gid    1 byte length (LEB128 of 16 = 0x10), then the 16 GID bytes

(33 bytes). ``std::array<uint8_t, 16>`` goes through the zenoh-ext serializer as a sequence, hence
the length byte; the deserializer rejects another length. The subscriber callback
(``rmw_subscription_data.cpp``) *drops a sample without attachment* ("Unable to obtain
attachment") and uses sequence number gaps per GID for the ``MESSAGE_LOST`` event. Jazzy's
rmw_zenoh_cpp before 0.2.4 (CHANGELOG: "Change serialization format in attachment_helpers.cpp",
#605, Apr 2025) used a keyed variant: the strings ``sequence_number``, ``source_timestamp`` and
``source_gid`` (zenoh-ext strings: LEB128 length + UTF-8) before each value (77 bytes). It is
offered as ``attachment_format="keyed"``; :func:`decode_attachment` reads both. rmw_zenoh
derives its publisher GID from a hash of the liveliness key (XXH3-128; older versions drew it at
random); subscribers treat it as opaque (message info, loss tracking), so a random GID stable per
publisher is used here.

**Liveliness tokens** (``docs/design.md`` "Graph Cache"; ``liveliness_utils.cpp``
``Entity::Entity``, ``qos_to_keyexpr``)::

    @ros2_lv/<domain_id>/<zid>/<node_id>/<node_id>/NN/<enclave>/<namespace>/<node_name>
    @ros2_lv/<domain_id>/<zid>/<node_id>/<entity_id>/<MP|MS|SS|SC>/<enclave>/<namespace>/
        <node_name>/<topic>/<type name>/<type hash>/<qos>

``zid`` is the Zenoh session id as Zenoh prints it; node and entity ids are decimal counters
of the context; every field is *mangled*: each ``/`` replaced by ``%``, so the root namespace
and the default enclave ``/`` are ``%`` and ``/chatter`` is ``%chatter``. ``ros2 topic list``
and ``ros2 node list`` are built from these tokens (the graph cache subscribes to
``@ros2_lv/<domain_id>/**``); ``@ros2_lv`` is a hermetic chunk that wildcards never match. The
graph cache rejects a token with an empty chunk or fewer than 13 chunks for a topic entity.

**QoS in the token** (``qos_to_keyexpr``)::

    <reliability>:<durability>:<history>,<depth>:<deadline s>,<ns>:<lifespan s>,<ns>:
        <liveliness>,<lease s>,<lease ns>

rmw enum values (``rmw/types.h``), each *left empty when equal to rmw_zenoh's default*
(``qos.cpp``: reliable, volatile, keep last, depth 42, durations infinite, liveliness
automatic); rclcpp's default ``QoS(10)`` is ``::,10:,:,:,,``. rmw_zenoh replaces system
defaults and depth 0 first (``best_available_qos``). There are no incompatible QoS in Zenoh
(``docs/design.md`` "Quality of Service"): any publisher reaches any subscriber on the same key,
the token's QoS is what ``ros2 topic info -v`` shows. A publisher maps RELIABLE to a reliable
Zenoh publisher, and RELIABLE + KEEP_ALL to ``CongestionControl.BLOCK`` (else DROP);
TRANSIENT_LOCAL adds a publication cache (``rmw_publisher_data.cpp``), not used here (the
bridge publishes no latched topic). Before rmw_zenoh_cpp 0.2.3 (#530) the default durability
was transient local, so such a robot reads an empty durability field as transient local
(``ros2 topic info -v`` only).

The pure functions (:func:`topic_key`, :func:`liveliness_token_key`, :func:`encode_attachment`,
:func:`decode_attachment`, :func:`qos_to_keyexpr`, :func:`type_hash`...) never import Zenoh;
:class:`RmwZenohAdapter` does, and :class:`RmwZenohAdapterPlugin` offers it as an ``--adapter``.
"""

from __future__ import annotations

import argparse
import dataclasses
import enum
import functools
import itertools
import logging
import os
import re
import secrets
import struct
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Final

from protocol.errors import UsageError
from robot_bridge.adapters.base import (
    POSE_STREAMS,
    LocalizationPose,
    RobotAdapter,
)
from robot_bridge.adapters.ros2 import (
    LOCALIZATION_TYPES,
    ODOMETRY_TYPE,
    POSE_WITH_COVARIANCE_STAMPED_TYPE,
    TF_MESSAGE_TYPE,
    RosAdapterBase,
    RosConversionError,
    RosTopics,
)

if TYPE_CHECKING:
    from protocol.site import Site
    from robot_bridge.adapters.registry import AdapterSetup

log = logging.getLogger(__name__)

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
ATTACHMENT_FORMATS: Final = ("compact", "keyed")
DEFAULT_NODE_NAME: Final = "smartedge_bridge"
#: the ROS environment variable rmw_zenoh reads the domain id from
DOMAIN_ID_ENV: Final = "ROS_DOMAIN_ID"

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
    SYSTEM_DEFAULT = 0
    RELIABLE = 1
    BEST_EFFORT = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class Durability(enum.IntEnum):
    SYSTEM_DEFAULT = 0
    TRANSIENT_LOCAL = 1
    VOLATILE = 2
    UNKNOWN = 3
    BEST_AVAILABLE = 4


class History(enum.IntEnum):
    SYSTEM_DEFAULT = 0
    KEEP_LAST = 1
    KEEP_ALL = 2
    UNKNOWN = 3


class Liveliness(enum.IntEnum):
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
#: the bridge's subscriptions (odometry, localization): best effort and volatile match every
#: publisher under DDS rules too; Zenoh itself matches any QoS
SUBSCRIPTION_QOS: Final = QosProfile(reliability=Reliability.BEST_EFFORT, depth=10)
#: corrections (initialpose / laser_2d_correct_pose): reliable, volatile, keep all, which
#: rmw_zenoh maps to a reliable publisher that blocks rather than drops under congestion
CORRECTION_QOS: Final = QosProfile(history=History.KEEP_ALL, depth=DEFAULT_DEPTH)
#: the continuous pose outputs: rclcpp's default QoS(10) (reliable, volatile)
POSE_OUTPUT_QOS: Final = QosProfile(depth=10)
#: /tf as tf2_ros's TransformBroadcaster publishes it (DynamicBroadcasterQoS: QoS(100))
TF_QOS: Final = QosProfile(depth=100)


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


def _check_domain_id(domain_id: int) -> int:
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
    return f"{_check_domain_id(domain_id)}/{name}/{dds_type_name(ros_type)}/{digest}"


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
    if not _NAME_TOKEN.fullmatch(str(node_name)):
        raise ValueError(f"invalid ROS node name {node_name!r}")
    for value, what in ((node_id, "node id"), (entity_id, "entity id")):
        if isinstance(value, bool) or not isinstance(value, int) or value < 0:
            raise ValueError(f"{what} {value!r}: expected an integer >= 0")
    if kind == NODE and entity_id != node_id:
        raise ValueError("a node's token carries its node id twice")
    enclave_abs = "/" if str(enclave).strip() in ("", "/") else "/" + str(enclave).strip("/")
    parts = [ADMIN_SPACE, str(_check_domain_id(domain_id)), str(zid), str(node_id),
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


def resolve_domain_id(value: int | None = None,
                      environ: Mapping[str, str] | None = None) -> int:
    """The ROS domain id: ``value`` when given, else ``$ROS_DOMAIN_ID`` (empty or unset: 0),
    as rcl reads it. :class:`UsageError` for a value that is not an integer >= 0."""
    if value is None:
        env = os.environ if environ is None else environ
        text = str(env.get(DOMAIN_ID_ENV, "")).strip()
        if not text:
            return 0
        if not text.isdigit():
            raise UsageError(f"{DOMAIN_ID_ENV}={text!r}: expected an integer >= 0")
        return int(text)
    try:
        return _check_domain_id(value)
    except ValueError as exc:
        raise UsageError(f"--ros-domain-id: {exc}") from None


# --------------------------------------------------------------------------------------------
# Zenoh transport
# --------------------------------------------------------------------------------------------

#: node and entity ids, unique in the process (rmw_zenoh counts per context)
_ENTITY_IDS = itertools.count()


@dataclasses.dataclass
class _Publisher:
    """One ROS publisher: its Zenoh publisher, its liveliness token, GID and next sequence
    number (rmw_zenoh starts at 1)."""

    topic: str
    key: str
    token_key: str
    gid: bytes
    zenoh_publisher: Any
    token: Any
    encode: Callable[[int, int, bytes], bytes]
    next_seq: int = 1

    def put(self, payload: bytes, now_ns: int) -> int:
        seq = self.next_seq
        self.next_seq += 1
        self.zenoh_publisher.put(payload, attachment=self.encode(seq, now_ns, self.gid))
        return seq


class RmwZenohAdapter(RosAdapterBase):
    """A ROS 2 robot (Jazzy or newer) on rmw_zenoh, reached directly over Zenoh.

    ``session``: an open ``zenoh.Session`` (not owned: the caller closes it) that reaches the
    robot's rmw_zenoh router. ``topics``: a :class:`RosTopics` (its ``namespace`` is the ROS
    namespace the bridge's node lives in; relative topic names resolve into it, absolute ones
    stay). The adapter is a ROS node ``node_name`` in ``domain_id``: it declares the node's
    liveliness token, an ``MS`` token and a subscriber for odometry (and localization), an
    ``MP`` token and a publisher for corrections; the pose outputs and ``/tf`` are declared on
    first use. Every sample it publishes carries the rmw_zenoh attachment (sequence from 1,
    source timestamp, a random GID per publisher; ``attachment_format="keyed"`` for
    rmw_zenoh_cpp < 0.2.4).

    It never blocks and never raises on robot data: samples are accepted with or without an
    attachment, and :attr:`counters` says what was wrong (``missing_attachment``,
    ``invalid_attachment``, ``messages_lost`` from sequence gaps, ``invalid_odometry``,
    ``invalid_localization``) besides what went through (``odometry``, ``localization``,
    ``corrections_published``, ``pose_fused_published``, ``tf_published``...).
    """

    name = "rmw_zenoh"

    def __init__(
        self, session: Any, topics: RosTopics | None = None, *, domain_id: int = 0,
        node_name: str = DEFAULT_NODE_NAME, namespace: str | None = None, enclave: str = "/",
        attachment_format: str = "compact", queue_size: int = 512,
    ) -> None:
        import zenoh

        super().__init__()
        self.topics = topics or RosTopics()
        if self.topics.ros1:
            raise ValueError("rmw_zenoh is ROS 2 only: RosTopics(ros1=True) is not supported")
        if self.topics.localization_type not in LOCALIZATION_TYPES:
            raise ValueError(
                f"localization_type {self.topics.localization_type!r}: expected one of "
                f"{LOCALIZATION_TYPES}")
        if attachment_format not in ATTACHMENT_FORMATS:
            raise ValueError(
                f"attachment_format {attachment_format!r}: expected one of {ATTACHMENT_FORMATS}")
        self.domain_id = _check_domain_id(domain_id)
        self.node_name = node_name
        self.namespace = node_namespace(self.topics.namespace if namespace is None else namespace)
        self.enclave = enclave
        self._encode = (encode_attachment if attachment_format == "compact"
                        else encode_keyed_attachment)
        self._session = session
        self.zid = str(session.info.zid())
        self.node_id = next(_ENTITY_IDS)
        self._closed = False
        self._latest_localization: LocalizationPose | None = None
        self._last_seq: dict[bytes, int] = {}
        #: (key, token) of the node and the subscriptions (publishers hold their own)
        self._tokens: list[tuple[str, Any]] = []
        self._subscribers: list[Any] = []
        self._publishers: dict[str, _Publisher] = {}

        # every name is checked before anything is declared
        odom_topic = self._resolve(self.topics.odometry_topic)
        loc_topic = (None if self.topics.localization_topic is None
                     else self._resolve(self.topics.localization_topic))
        correction_topic = self._resolve(self.topics.correction_topic)
        self._output_topics = {
            stream: self._resolve(self.topics.pose_output_topic(stream))
            for stream in POSE_STREAMS}
        self._tf_topic = self._resolve(self.topics.tf_topic)
        node_token = self._token_key(NODE, self.node_id)
        try:
            self._tokens.append((node_token, session.liveliness().declare_token(node_token)))
            self._odom_sub = self._subscribe(
                odom_topic, ODOMETRY_TYPE, zenoh.handlers.RingChannel(queue_size))
            self._loc_sub = (None if loc_topic is None else self._subscribe(
                loc_topic, self.topics.localization_type, zenoh.handlers.RingChannel(16)))
            self._correction_pub = self._advertise(
                correction_topic, POSE_WITH_COVARIANCE_STAMPED_TYPE, CORRECTION_QOS)
        except Exception:
            self.close()
            raise
        log.info("rmw_zenoh node %s%s%s in domain %d (zid %s): odometry %s, corrections %s",
                 self.namespace, "" if self.namespace == "/" else "/", node_name,
                 self.domain_id, self.zid, odom_topic, correction_topic)

    # -- declarations ------------------------------------------------------------------------

    def _resolve(self, topic: str) -> str:
        return fully_qualified_name(topic, self.namespace)

    def _token_key(self, kind: str, entity_id: int, topic: str | None = None,
                   ros_type: str | None = None, qos: QosProfile | None = None) -> str:
        return liveliness_token_key(
            self.domain_id, self.zid, self.node_id, entity_id, kind, node_name=self.node_name,
            namespace=self.namespace, enclave=self.enclave, topic=topic, ros_type=ros_type,
            qos=qos)

    def _subscribe(self, topic: str, ros_type: str, handler: Any) -> Any:
        key = topic_key(self.domain_id, topic, ros_type)
        token_key = self._token_key(SUBSCRIPTION, next(_ENTITY_IDS), topic, ros_type,
                                    SUBSCRIPTION_QOS)
        subscriber = self._session.declare_subscriber(key, handler)
        self._subscribers.append(subscriber)
        self._tokens.append((token_key, self._session.liveliness().declare_token(token_key)))
        log.debug("subscribed %s (%s)", key, token_key)
        return subscriber

    def _advertise(self, topic: str, ros_type: str, qos: QosProfile) -> _Publisher:
        import zenoh

        key = topic_key(self.domain_id, topic, ros_type)
        qos = adapt_qos(qos)
        token_key = self._token_key(PUBLISHER, next(_ENTITY_IDS), topic, ros_type, qos)
        reliable, block = zenoh_publication_mode(qos)
        zenoh_publisher = self._session.declare_publisher(
            key,
            reliability=(zenoh.Reliability.RELIABLE if reliable
                         else zenoh.Reliability.BEST_EFFORT),
            congestion_control=(zenoh.CongestionControl.BLOCK if block
                                else zenoh.CongestionControl.DROP),
        )
        try:
            token = self._session.liveliness().declare_token(token_key)
        except Exception:
            zenoh_publisher.undeclare()
            raise
        publisher = _Publisher(topic, key, token_key, secrets.token_bytes(GID_SIZE),
                               zenoh_publisher, token, self._encode)
        self._publishers[topic] = publisher
        log.debug("advertised %s (%s)", key, token_key)
        return publisher

    def _output(self, topic: str, ros_type: str, qos: QosProfile) -> _Publisher:
        publisher = self._publishers.get(topic)
        if publisher is None:
            publisher = self._advertise(topic, ros_type, qos)
        return publisher

    def token_keys(self) -> list[str]:
        """The liveliness keys this adapter has declared: the node's, the subscriptions', then
        the publishers' (for logs and tests)."""
        return [key for key, _ in self._tokens] + [
            p.token_key for p in self._publishers.values()]

    # -- robot -> bridge ---------------------------------------------------------------------

    def _check_attachment(self, attachment: Any) -> None:
        if attachment is None:
            # rmw_zenoh itself would drop such a sample; the payload is still a valid message
            self._count("missing_attachment")
            return
        try:
            info = decode_attachment(attachment.to_bytes())
        except AttachmentError as exc:
            self._count("invalid_attachment")
            log.debug("invalid attachment: %s", exc)
            return
        last = self._last_seq.get(info.source_gid)
        if last is not None and abs(info.sequence_number - last) > 1:
            self._count("messages_lost", abs(info.sequence_number - last) - 1)
        self._last_seq[info.source_gid] = info.sequence_number

    def _drain(self, subscriber: Any) -> list[bytes]:
        out: list[bytes] = []
        while True:
            sample = subscriber.try_recv()
            if sample is None:
                return out
            self._check_attachment(sample.attachment)
            out.append(sample.payload.to_bytes())

    # -- bridge -> robot ---------------------------------------------------------------------

    def _send(self, target: str, payload: bytes) -> None:
        if target == "correction":
            publisher = self._correction_pub
        elif target == "tf":
            publisher = self._output(self._tf_topic, TF_MESSAGE_TYPE, TF_QOS)
        else:
            publisher = self._output(self._output_topics[target.removeprefix("pose_")],
                                     POSE_WITH_COVARIANCE_STAMPED_TYPE, POSE_OUTPUT_QOS)
        publisher.put(payload, time.time_ns())

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        # entity tokens go first and the node's last, as rmw_zenoh shuts entities down
        entities = [token for _, token in self._tokens[1:]]
        for publisher in self._publishers.values():
            entities += [publisher.token, publisher.zenoh_publisher]
        entities += [*self._subscribers, *(token for _, token in self._tokens[:1])]
        for entity in entities:
            try:
                entity.undeclare()
            except Exception:  # session already closed
                log.debug("undeclare failed", exc_info=True)


# --------------------------------------------------------------------------------------------
# --adapter plug-in
# --------------------------------------------------------------------------------------------


class RmwZenohAdapterPlugin:
    """``--adapter rmw_zenoh``: a ROS 2 Jazzy+ robot on rmw_zenoh through
    :class:`RmwZenohAdapter`. Adds ``--ros-domain-id``, ``--ros-node-name`` and
    ``--rmw-zenoh-attachment``; reads the ROS plug-in's ``--robot-profile``,
    ``--ros-namespace`` (here: the ROS namespace of the robot's topics), ``--correction-topic``
    and ``--odom-topic`` when they are there."""

    def add_arguments(self, parser: argparse.ArgumentParser) -> None:
        group = parser.add_argument_group(
            "rmw_zenoh adapter (ROS 2 Jazzy+ on rmw_zenoh; also reads --robot-profile, "
            "--ros-namespace, --correction-topic, --odom-topic)")
        group.add_argument(
            "--ros-domain-id", type=int, default=None, metavar="N",
            help=f"the robot's ROS domain id (default: ${DOMAIN_ID_ENV}, else 0)")
        group.add_argument(
            "--ros-node-name", default=DEFAULT_NODE_NAME,
            help="node name the bridge shows in `ros2 node list`")
        group.add_argument(
            "--rmw-zenoh-attachment", choices=ATTACHMENT_FORMATS, default="compact",
            help="attachment layout: compact (rmw_zenoh_cpp >= 0.2.4, Kilted, Rolling) or "
                 "keyed (Jazzy rmw_zenoh_cpp 0.2.0-0.2.3)")

    def build(self, args: argparse.Namespace, site: Site | None) -> AdapterSetup:
        # rosbags (the CDR codec and type hashes) is an extra: imported when the adapter is used
        from robot_bridge.adapters.registry import AdapterSetup, ros_config

        # the site file's ros section with the ROS plug-in's command-line overrides; corrections
        # and pose outputs are poses in the site's world frame
        config = ros_config(args, site)  # UsageError without a site
        assert site is not None
        topics = config.topics(map_frame=site.world_frame)
        namespace = config.namespace
        # --ros-domain-id, else $ROS_DOMAIN_ID when set, else the site file's ros.domain_id
        domain_id = resolve_domain_id(getattr(args, "ros_domain_id", None),
                                      {DOMAIN_ID_ENV: str(config.domain_id),
                                       **{k: v for k, v in os.environ.items()
                                          if k == DOMAIN_ID_ENV and v.strip()}})
        node_name = getattr(args, "ros_node_name", DEFAULT_NODE_NAME)
        attachment_format = getattr(args, "rmw_zenoh_attachment", "compact")
        # names are checked now, so a typo is a usage error before any session is opened
        for topic in (topics.odometry_topic, topics.correction_topic):
            fully_qualified_name(topic, namespace)
        if not _NAME_TOKEN.fullmatch(node_name):
            raise UsageError(f"--ros-node-name {node_name!r} is not a valid ROS node name")

        def factory(session: Any) -> RobotAdapter:
            return RmwZenohAdapter(session, topics, domain_id=domain_id, node_name=node_name,
                                   attachment_format=attachment_format)

        return AdapterSetup(factory)


RMW_ZENOH_ADAPTER = RmwZenohAdapterPlugin()
