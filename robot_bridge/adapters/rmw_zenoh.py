"""ROS 2 robots on rmw_zenoh (Jazzy and newer), reached directly: no bridge process.

With ``RMW_IMPLEMENTATION=rmw_zenoh_cpp`` every ROS 2 node is a Zenoh session, so the bridge
is a ROS node itself on its own Zenoh session: :class:`RmwZenohAdapter` declares the node's
liveliness token, subscribes to odometry (and localization) and publishes corrections and the
pose outputs with the rmw_zenoh attachment; :class:`RmwZenohAdapterPlugin` offers it as
``--adapter rmw_zenoh``. The keys, attachment, tokens and QoS encoding are the pure functions
of :mod:`robot_bridge.adapters.rmw_zenoh_wire`; the CDR payloads are
:mod:`robot_bridge.adapters.ros2`'s codecs.

docs/robot_bridge.md, "ROS 2 on rmw_zenoh", says what goes over the wire (with the upstream
sources), how to connect the robot's router, and the version notes. Upstream behaviour followed
here: ``rmw_subscription_data.cpp`` (a sample without attachment is dropped there, sequence
gaps per GID are ``MESSAGE_LOST``), ``rmw_publisher_data.cpp`` (reliability and congestion
control of a publisher, sequence numbers from 1), ``liveliness_utils.cpp`` (entity tokens).
"""

from __future__ import annotations

import argparse
import dataclasses
import itertools
import logging
import os
import secrets
import time
from collections.abc import Callable, Mapping
from typing import TYPE_CHECKING, Any, Final

from protocol.errors import UsageError
from robot_bridge.adapters.base import (
    POSE_STREAMS,
    AdapterSetup,
    LocalizationPose,
    RobotAdapter,
)
from robot_bridge.adapters.rmw_zenoh_wire import (
    ATTACHMENT_FORMATS,
    DEFAULT_DEPTH,
    GID_SIZE,
    NODE,
    PUBLISHER,
    SUBSCRIPTION,
    AttachmentError,
    History,
    QosProfile,
    Reliability,
    adapt_qos,
    check_domain_id,
    decode_attachment,
    encode_attachment,
    encode_keyed_attachment,
    fully_qualified_name,
    is_node_name,
    liveliness_token_key,
    node_namespace,
    topic_key,
    zenoh_publication_mode,
)
from robot_bridge.adapters.ros2 import (
    LOCALIZATION_TYPES,
    OCCUPANCY_GRID_TYPE,
    ODOMETRY_TYPE,
    POINT_CLOUD2_TYPE,
    POSE_WITH_COVARIANCE_STAMPED_TYPE,
    TF_MESSAGE_TYPE,
    RosAdapterBase,
    RosTopics,
)
from robot_bridge.adapters.ros_plugin import ros_config

if TYPE_CHECKING:
    from core.site import Site

log = logging.getLogger(__name__)

DEFAULT_NODE_NAME: Final = "smartedge_bridge"
#: the ROS environment variable rmw_zenoh reads the domain id from
DOMAIN_ID_ENV: Final = "ROS_DOMAIN_ID"

# the QoS each of the bridge's entities announces in its token (Zenoh itself matches any QoS)

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
#: the semantic map and its obstacle grid: reliable, volatile, keep last 1 (a new map replaces
#: an old one; RViz's default subscription and Nav2's static layer with
#: ``map_subscribe_transient_local: false`` match it)
MAP_QOS: Final = QosProfile(depth=1)


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
        return check_domain_id(value)
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
    ``corrections_published``, ``pose_fused_published``, ``tf_published``,
    ``map_cloud_published``, ``map_grid_published``...).
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
        self.domain_id = check_domain_id(domain_id)
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
        self._map_cloud_topic = self._resolve(self.topics.map_cloud_topic)
        self._obstacles_topic = self._resolve(self.topics.obstacles_topic)
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
        elif target == "map_cloud":
            publisher = self._output(self._map_cloud_topic, POINT_CLOUD2_TYPE, MAP_QOS)
        elif target == "map_grid":
            publisher = self._output(self._obstacles_topic, OCCUPANCY_GRID_TYPE, MAP_QOS)
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
        if not is_node_name(node_name):
            raise UsageError(f"--ros-node-name {node_name!r} is not a valid ROS node name")

        def factory(session: Any) -> RobotAdapter:
            return RmwZenohAdapter(session, topics, domain_id=domain_id, node_name=node_name,
                                   attachment_format=attachment_format)

        return AdapterSetup(factory)


RMW_ZENOH_ADAPTER = RmwZenohAdapterPlugin()
