"""``smartedge sim-head``: the simulated robot's moving head as a ROS 2 robot publishes it.

A real HSR publishes its head camera's RGB-D frames and its joints' frames as ROS 2 topics;
``smartedge robot-camera --source ros`` turns those into semantic clouds in ``base_link``,
looking the camera's pose up in ``/tf`` at each image's stamp. This service is that robot for
the simulation, so the simulated demo exercises the same path:

* ``/tf`` (``tf2_msgs/TFMessage``): ``torso_lift_link`` -> ``head_pan_link`` (pan) and
  ``head_pan_link`` -> ``head_tilt_link`` (tilt) at ``--tf-rate`` (30 Hz), stamped with the
  simulation's time on a grid offset from the camera's (images fall between two of them, as on
  a robot whose joint states and camera are not synchronised);
* ``/tf_static``: ``base_link`` -> ``torso_lift_link`` and ``head_tilt_link`` ->
  ``head_rgbd_sensor_rgb_frame`` (the optical frame), transient local as tf2's static
  broadcaster (under rmw_zenoh a Zenoh ``AdvancedPublisher`` whose cache of the last message a
  late ``AdvancedSubscriber`` with history queries, as rmw_zenoh does), and repeated once a
  second for subscribers that only listen;
* ``/hsrb/head_rgbd_sensor/rgb/image_rect_color`` (``sensor_msgs/Image`` rgb8),
  ``/hsrb/head_rgbd_sensor/depth_registered/image_rect_raw`` (``16UC1``, millimetres, 0 = no
  depth, aligned to the colour image) and ``/hsrb/head_rgbd_sensor/rgb/camera_info`` at
  ``--rate`` (2 Hz), header stamp = capture time, ``frame_id`` = the optical frame.

Frames are rendered from the robot's *true* pose with the head's *true* pan and tilt at the
capture time (:class:`simulation.live.HeadCameraFeed` with a :class:`simulation.head.
SimulatedHead`; sensor and depth noise as that feed adds them). The simulated lens has the
site file's distortion, which ``CameraInfo`` carries (the topic name is the HSR's, the image is
not rectified). Messages are CDR made with rosbags; over ``--ros-transport rmw_zenoh`` (the
default) the keys, the sample attachment and the liveliness tokens of a node and its
publishers are spelled as rmw_zenoh does (:mod:`robot_bridge.adapters.rmw_zenoh_wire`); over
``ros2dds`` the keys are zenoh-bridge-ros2dds' plain topic names.

Simulation only (top floor: it joins the simulation and the ROS wire code).
"""

from __future__ import annotations

import argparse
import collections
import dataclasses
import logging
import math
import secrets
import time
from collections.abc import Callable, Iterable, Sequence
from typing import TYPE_CHECKING, Any, Final

import numpy as np

from core.geometry import rotation_to_quaternion
from core.runtime import Outgoing, ServiceNode, service_main
from core.session import add_session_arguments
from core.site import HeadCamera, Site
from protocol.errors import UsageError
from protocol.messages import NS_PER_S
from simulation.head import CAMERA_FRAME, FrameTransform, SimulatedHead

if TYPE_CHECKING:
    from simulation.live import HeadCameraFeed

log = logging.getLogger(__name__)

TF_TOPIC: Final = "/tf"
TF_STATIC_TOPIC: Final = "/tf_static"
#: the HSR's head RGB-D topics (hsrb_interface / hsrb_common)
COLOR_TOPIC: Final = "/hsrb/head_rgbd_sensor/rgb/image_rect_color"
DEPTH_TOPIC: Final = "/hsrb/head_rgbd_sensor/depth_registered/image_rect_raw"
CAMERA_INFO_TOPIC: Final = "/hsrb/head_rgbd_sensor/rgb/camera_info"

TF_MESSAGE_TYPE: Final = "tf2_msgs/msg/TFMessage"
IMAGE_TYPE: Final = "sensor_msgs/msg/Image"
CAMERA_INFO_TYPE: Final = "sensor_msgs/msg/CameraInfo"

DEFAULT_RATE_HZ: Final = 2.0
DEFAULT_TF_RATE_HZ: Final = 30.0
DEFAULT_STATIC_PERIOD_S: Final = 1.0
#: where the /tf grid sits inside one period (a fraction of it): images at k / rate fall
#: between two transforms
TF_PHASE_FRACTION: Final = 0.37
#: at most this many seconds of missed /tf stamps are published after a stall; older ones
#: are skipped (counted ``tf_skipped``)
MAX_TF_CATCH_UP_S: Final = 0.5
#: frames whose cost :attr:`HeadRosStream.frame_costs_ms` keeps
COSTS_KEPT: Final = 256
#: the status says ``degraded`` this long after /tf stamps were skipped
RECENT_STALL_S: Final = 10.0
DEFAULT_NODE_NAME: Final = "hsrb_sim_head"
TRANSPORTS: Final = ("rmw_zenoh", "ros2dds")
#: 16UC1 depth: millimetres, 0 = no depth, the largest value a uint16 holds
DEPTH_MAX_MM: Final = 65535


@dataclasses.dataclass(frozen=True)
class RosMessage:
    """One ROS message ready for the wire: ``topic``, ``ros_type``, CDR ``payload`` and the
    header stamp (ns; for a TFMessage the stamp of its transforms)."""

    topic: str
    ros_type: str
    payload: bytes
    stamp_ns: int


# --------------------------------------------------------------------------------------------
# messages (rosbags)
# --------------------------------------------------------------------------------------------


def _typestore() -> Any:
    from robot_bridge.adapters.ros2 import typestore

    return typestore()


def _header(ts: Any, stamp_ns: int, frame_id: str) -> Any:
    from robot_bridge.adapters.ros2 import stamp_ns_to_ros

    sec, nanosec = stamp_ns_to_ros(stamp_ns)
    return ts.types["std_msgs/msg/Header"](
        stamp=ts.types["builtin_interfaces/msg/Time"](sec=sec, nanosec=nanosec),
        frame_id=frame_id)


def tf_message_cdr(transforms: Sequence[FrameTransform], stamp_ns: int) -> bytes:
    """A ``tf2_msgs/msg/TFMessage`` (CDR) holding ``transforms``, all stamped ``stamp_ns``."""
    ts = _typestore()
    t = ts.types
    items = []
    for tr in transforms:
        T = np.asarray(tr.T_parent_child, np.float64)
        qx, qy, qz, qw = rotation_to_quaternion(T[:3, :3])
        items.append(t["geometry_msgs/msg/TransformStamped"](
            header=_header(ts, stamp_ns, tr.parent), child_frame_id=tr.child,
            transform=t["geometry_msgs/msg/Transform"](
                translation=t["geometry_msgs/msg/Vector3"](
                    x=float(T[0, 3]), y=float(T[1, 3]), z=float(T[2, 3])),
                rotation=t["geometry_msgs/msg/Quaternion"](x=qx, y=qy, z=qz, w=qw))))
    return bytes(ts.serialize_cdr(t[TF_MESSAGE_TYPE](transforms=items), TF_MESSAGE_TYPE))


def image_cdr(pixels: np.ndarray, encoding: str, stamp_ns: int, frame_id: str) -> bytes:
    """A ``sensor_msgs/msg/Image`` (CDR, little endian, unpadded rows) of ``pixels``: (H, W, 3)
    uint8 for ``rgb8``, (H, W) uint16 for ``16UC1``."""
    ts = _typestore()
    arr = np.ascontiguousarray(pixels)
    if encoding == "rgb8" and (arr.dtype != np.uint8 or arr.ndim != 3 or arr.shape[2] != 3):
        raise ValueError(f"rgb8 image: expected (H, W, 3) uint8, got {arr.shape} {arr.dtype}")
    if encoding == "16UC1" and (arr.dtype != np.uint16 or arr.ndim != 2):
        raise ValueError(f"16UC1 image: expected (H, W) uint16, got {arr.shape} {arr.dtype}")
    if encoding not in ("rgb8", "16UC1"):
        raise ValueError(f"image encoding {encoding!r}: only rgb8 and 16UC1 are published")
    h, w = arr.shape[:2]
    data = arr.astype(arr.dtype.newbyteorder("<"), copy=False).view(np.uint8).reshape(-1)
    msg = ts.types[IMAGE_TYPE](header=_header(ts, stamp_ns, frame_id), height=h, width=w,
                               encoding=encoding, is_bigendian=0, step=data.size // h,
                               data=data)
    return bytes(ts.serialize_cdr(msg, IMAGE_TYPE))


def depth_to_mm(depth_m: np.ndarray) -> np.ndarray:
    """(H, W) float depth in metres (0, inf or NaN = none) → (H, W) uint16 millimetres, as
    ``16UC1`` depth carries it (0 = none; beyond 65.535 m: none)."""
    z = np.asarray(depth_m, np.float64)
    ok = np.isfinite(z) & (z > 0.0)
    mm = np.where(ok, np.rint(np.where(ok, z, 0.0) * 1000.0), 0.0)
    mm[mm > DEPTH_MAX_MM] = 0.0
    return mm.astype(np.uint16)


def camera_info_cdr(head: HeadCamera, stamp_ns: int, frame_id: str) -> bytes:
    """The head camera's ``sensor_msgs/msg/CameraInfo`` (CDR): size, K, the distortion
    (``plumb_bob`` for 5 coefficients or fewer, ``rational_polynomial`` for 8), R = I,
    P = [K | 0]."""
    ts = _typestore()
    dist = np.zeros(5) if head.dist.size == 0 else np.asarray(head.dist, np.float64).reshape(-1)
    if dist.size < 5:
        dist = np.concatenate([dist, np.zeros(5 - dist.size)])
    model = "plumb_bob" if dist.size == 5 else "rational_polynomial"
    K = np.asarray(head.K, np.float64)
    P = np.zeros((3, 4))
    P[:, :3] = K
    roi = ts.types["sensor_msgs/msg/RegionOfInterest"](
        x_offset=0, y_offset=0, height=0, width=0, do_rectify=False)
    msg = ts.types[CAMERA_INFO_TYPE](
        header=_header(ts, stamp_ns, frame_id), height=int(head.height),
        width=int(head.width), distortion_model=model, d=dist, k=K.reshape(-1),
        r=np.eye(3).reshape(-1), p=P.reshape(-1), binning_x=0, binning_y=0, roi=roi)
    return bytes(ts.serialize_cdr(msg, CAMERA_INFO_TYPE))


# --------------------------------------------------------------------------------------------
# what is due when (transport-free)
# --------------------------------------------------------------------------------------------


class HeadRosStream:
    """The head's ROS messages in time: :meth:`due` returns every message due at ``now_ns``.

    ``head``: the moving head (its TF); ``feed``: the head camera (``due``, ``render``; ``None``:
    TF only); ``tf_rate_hz``: ``/tf`` stamps on ``epoch + phase + k / tf_rate_hz``;
    ``static_period_s``: ``/tf_static`` again after this long. ``counters``: messages by topic
    and the skipped ones; ``render_ms`` and ``encode_ms``: the last frame's cost (rendering
    with noise; CDR of its three messages), :attr:`frame_costs_ms` the recent ones'."""

    def __init__(self, head: SimulatedHead, feed: HeadCameraFeed | None, *,
                 tf_rate_hz: float = DEFAULT_TF_RATE_HZ,
                 static_period_s: float = DEFAULT_STATIC_PERIOD_S) -> None:
        if not (math.isfinite(tf_rate_hz) and tf_rate_hz > 0.0):
            raise ValueError(f"/tf rate {tf_rate_hz} Hz: must be > 0")
        if not (math.isfinite(static_period_s) and static_period_s > 0.0):
            raise ValueError(f"/tf_static period {static_period_s} s: must be > 0")
        self.head = head
        self.feed = feed
        self._tf_period_ns = round(NS_PER_S / tf_rate_hz)
        self._tf_phase_ns = round(TF_PHASE_FRACTION * self._tf_period_ns)
        self._static_period_ns = round(static_period_s * NS_PER_S)
        self._next_tf: int | None = None
        self._next_static_ns: int | None = None
        self.counters: dict[str, int] = {"tf": 0, "tf_static": 0, "images": 0,
                                         "tf_skipped": 0}
        self.render_ms = 0.0
        self.encode_ms = 0.0
        #: (render, encode) milliseconds of the recent frames
        self.frame_costs_ms: collections.deque[tuple[float, float]] = collections.deque(
            maxlen=COSTS_KEPT)

    def tf_stamp(self, k: int) -> int:
        return self.head.epoch_ns + self._tf_phase_ns + k * self._tf_period_ns

    def _tf_due(self, now_ns: int) -> list[RosMessage]:
        newest = (now_ns - self.tf_stamp(0)) // self._tf_period_ns
        if self._next_tf is None:
            self._next_tf = int(newest)
        first = max(self._next_tf, int(newest) - round(MAX_TF_CATCH_UP_S * NS_PER_S
                                                       / self._tf_period_ns))
        self.counters["tf_skipped"] += max(0, first - self._next_tf)
        out = []
        for k in range(first, int(newest) + 1):
            stamp = self.tf_stamp(k)
            out.append(RosMessage(TF_TOPIC, TF_MESSAGE_TYPE,
                                  tf_message_cdr(self.head.dynamic_transforms(stamp), stamp),
                                  stamp))
        self._next_tf = max(self._next_tf, int(newest) + 1)
        self.counters["tf"] += len(out)
        return out

    def _static_due(self, now_ns: int) -> list[RosMessage]:
        if self._next_static_ns is not None and now_ns < self._next_static_ns:
            return []
        self._next_static_ns = now_ns + self._static_period_ns
        self.counters["tf_static"] += 1
        return [RosMessage(TF_STATIC_TOPIC, TF_MESSAGE_TYPE,
                           tf_message_cdr(self.head.static_transforms(), now_ns), now_ns)]

    def _frame_due(self, now_ns: int) -> list[RosMessage]:
        if self.feed is None:
            return []
        capture_ns = self.feed.due(now_ns)
        if capture_ns is None:
            return []
        t0 = time.perf_counter()
        rgb, depth_m, _ = self.feed.render(capture_ns)
        t1 = time.perf_counter()
        out = [
            RosMessage(COLOR_TOPIC, IMAGE_TYPE,
                       image_cdr(rgb, "rgb8", capture_ns, CAMERA_FRAME), capture_ns),
            RosMessage(DEPTH_TOPIC, IMAGE_TYPE,
                       image_cdr(depth_to_mm(depth_m), "16UC1", capture_ns, CAMERA_FRAME),
                       capture_ns),
            RosMessage(CAMERA_INFO_TOPIC, CAMERA_INFO_TYPE,
                       camera_info_cdr(self.feed.head, capture_ns, CAMERA_FRAME), capture_ns),
        ]
        self.render_ms = (t1 - t0) * 1e3
        self.encode_ms = (time.perf_counter() - t1) * 1e3
        self.frame_costs_ms.append((self.render_ms, self.encode_ms))
        self.counters["images"] += 1
        return out

    def warm_up(self) -> None:
        """Create the renderer and draw one frame now (the GL context and the site's meshes
        take most of a second on the first frame, which would otherwise stall ``/tf``)."""
        if self.feed is None:
            return
        feed = self.feed
        t0 = time.perf_counter()
        stamp = self.head.epoch_ns
        out = feed.images.render_head(feed.head, feed.live.ground_truth(stamp), feed.camera_id,
                                      self.head.T_base_cam(stamp))
        if feed.images.noise.sigma_dn > 0:  # the sensor-noise bank, drawn on first use
            feed.images.add_noise(out.color_rgb, np.random.default_rng(0))
        log.info("head camera renderer ready in %.0f ms", (time.perf_counter() - t0) * 1e3)

    def due(self, now_ns: int) -> list[RosMessage]:
        """Every message due at ``now_ns``, in publishing order: ``/tf_static`` when due, the
        ``/tf`` stamps up to ``now_ns``, then a camera frame when one is due (its three
        messages)."""
        return self._static_due(now_ns) + self._tf_due(now_ns) + self._frame_due(now_ns)


# --------------------------------------------------------------------------------------------
# transport: ROS 2 publishers on Zenoh
# --------------------------------------------------------------------------------------------


@dataclasses.dataclass
class _RosPublisher:
    key: str
    token_key: str | None
    zenoh_publisher: Any
    token: Any
    gid: bytes
    next_seq: int = 1


class RosZenohPublishers:
    """ROS 2 publishers on an open Zenoh session (not owned): ``rmw_zenoh`` (keys with the
    type hash, the 33-byte attachment with sequence numbers from 1, a random GID per publisher,
    liveliness tokens for the node and each publisher) or ``ros2dds`` (plain keys under
    ``namespace``, no attachment, no tokens)."""

    def __init__(self, session: Any, *, transport: str = "rmw_zenoh", domain_id: int = 0,
                 node_name: str = DEFAULT_NODE_NAME, namespace: str = "") -> None:
        from robot_bridge.adapters.rmw_zenoh_wire import (
            NODE,
            check_domain_id,
            is_node_name,
            liveliness_token_key,
        )

        if transport not in TRANSPORTS:
            raise UsageError(f"--ros-transport {transport!r}: expected one of {TRANSPORTS}")
        if not is_node_name(node_name):
            raise UsageError(f"--ros-node-name {node_name!r} is not a valid ROS node name")
        try:
            self.domain_id = check_domain_id(domain_id)
        except ValueError as exc:
            raise UsageError(f"--ros-domain-id: {exc}") from None
        self.session = session
        self.transport = transport
        self.node_name = node_name
        self.namespace = namespace
        self.zid = str(session.info.zid())
        self._publishers: dict[str, _RosPublisher] = {}
        self._tokens: list[Any] = []
        self._entity_ids = iter(range(1, 1 << 30))
        self.node_id = 0
        self.node_token_key: str | None = None
        if transport == "rmw_zenoh":
            self.node_token_key = liveliness_token_key(
                self.domain_id, self.zid, self.node_id, self.node_id, NODE,
                node_name=node_name, namespace=namespace or "/")
            self._tokens.append(session.liveliness().declare_token(self.node_token_key))

    def advertise(self, topic: str, ros_type: str, qos: Any = None) -> None:
        """Declare the publisher of ``topic`` (and its liveliness token under rmw_zenoh)."""
        import zenoh

        from robot_bridge.adapters.rmw_zenoh_wire import (
            PUBLISHER,
            Durability,
            QosProfile,
            adapt_qos,
            fully_qualified_name,
            liveliness_token_key,
            topic_key,
            zenoh_publication_mode,
        )
        from robot_bridge.adapters.ros2 import ros2dds_key

        qos = adapt_qos(qos or QosProfile(depth=10))
        reliable, block = zenoh_publication_mode(qos)
        token_key = None
        if self.transport == "rmw_zenoh":
            fqn = fully_qualified_name(topic, self.namespace or "/")
            key = topic_key(self.domain_id, fqn, ros_type)
            token_key = liveliness_token_key(
                self.domain_id, self.zid, self.node_id, next(self._entity_ids), PUBLISHER,
                node_name=self.node_name, namespace=self.namespace or "/", topic=fqn,
                ros_type=ros_type, qos=qos)
        else:
            key = ros2dds_key(topic, self.namespace)
        options = dict(
            reliability=zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT,
            congestion_control=(zenoh.CongestionControl.BLOCK if block
                                else zenoh.CongestionControl.DROP))
        pub = None
        if qos.durability == Durability.TRANSIENT_LOCAL:
            # as rmw_zenoh: a cache of the last ``depth`` samples that late subscribers query
            # (an AdvancedSubscriber with history), and publisher detection; samples are
            # sequenced by number (sample miss detection), so the session needs no timestamping
            try:
                import zenoh.ext as zext

                pub = zext.declare_advanced_publisher(
                    self.session, key, cache=zext.CacheConfig(max_samples=qos.depth),
                    publisher_detection=True,
                    sample_miss_detection=zext.MissDetectionConfig(
                        heartbeat=None, sporadic_heartbeat=None),
                    **options)
            except Exception as exc:  # no zenoh.ext, or a Zenoh that refuses the options
                log.warning("%s: no Zenoh AdvancedPublisher (%s): published without a cache "
                            "(repeated instead)", topic, exc)
        if pub is None:
            pub = self.session.declare_publisher(key, **options)
        token = None if token_key is None else self.session.liveliness().declare_token(token_key)
        self._publishers[topic] = _RosPublisher(key, token_key, pub, token,
                                                secrets.token_bytes(16))
        log.debug("advertised %s on %s", topic, key)

    def keys(self) -> dict[str, str]:
        """topic → the Zenoh key it is published on."""
        return {topic: p.key for topic, p in self._publishers.items()}

    def token_keys(self) -> list[str]:
        """The liveliness keys declared: the node's, then the publishers' (rmw_zenoh)."""
        return ([] if self.node_token_key is None else [self.node_token_key]) + [
            p.token_key for p in self._publishers.values() if p.token_key is not None]

    def put(self, message: RosMessage) -> None:
        from robot_bridge.adapters.rmw_zenoh_wire import encode_attachment

        pub = self._publishers[message.topic]
        if self.transport == "rmw_zenoh":
            attachment = encode_attachment(pub.next_seq, time.time_ns(), pub.gid)
            pub.zenoh_publisher.put(message.payload, attachment=attachment)
        else:
            pub.zenoh_publisher.put(message.payload)
        pub.next_seq += 1

    def close(self) -> None:
        for pub in self._publishers.values():
            if pub.token is not None:
                pub.token.undeclare()
            pub.zenoh_publisher.undeclare()
        for token in self._tokens:
            token.undeclare()
        self._publishers.clear()
        self._tokens.clear()


def _qos_by_topic() -> dict[str, Any]:
    from robot_bridge.adapters.rmw_zenoh_wire import Durability, QosProfile

    return {
        TF_TOPIC: QosProfile(depth=100),  # tf2_ros's DynamicBroadcasterQoS
        # tf2_ros's StaticBroadcasterQoS: transient local, keep last 1 (and repeated at 1 Hz)
        TF_STATIC_TOPIC: QosProfile(durability=Durability.TRANSIENT_LOCAL, depth=1),
        COLOR_TOPIC: QosProfile(depth=10),
        DEPTH_TOPIC: QosProfile(depth=10),
        CAMERA_INFO_TOPIC: QosProfile(depth=10),
    }


TOPIC_TYPES: Final = {TF_TOPIC: TF_MESSAGE_TYPE, TF_STATIC_TOPIC: TF_MESSAGE_TYPE,
                      COLOR_TOPIC: IMAGE_TYPE, DEPTH_TOPIC: IMAGE_TYPE,
                      CAMERA_INFO_TOPIC: CAMERA_INFO_TYPE}


# --------------------------------------------------------------------------------------------
# the service
# --------------------------------------------------------------------------------------------


class HeadRosNode(ServiceNode):
    """Publishes :class:`HeadRosStream`'s messages when due. On a Zenoh runner the ROS
    publishers are declared in :meth:`attach`; ``sink``: where messages go instead (tests,
    benchmarks; called with each :class:`RosMessage`)."""

    service = "sim-head"
    tick_period_s = 0.01

    def __init__(self, site: Site, robot_id: str, stream: HeadRosStream, *,
                 transport: str = "rmw_zenoh", domain_id: int = 0,
                 node_name: str = DEFAULT_NODE_NAME, namespace: str = "",
                 sink: Callable[[RosMessage], None] | None = None) -> None:
        super().__init__(site.name, robot_id)
        self.stream = stream
        self.transport = transport
        self.domain_id = domain_id
        self.node_name = node_name
        self.namespace = namespace
        self.sink = sink
        self.publishers: RosZenohPublishers | None = None
        self._skipped_seen = 0
        self._skipped_at_s: float | None = None

    def attach(self, session: Any) -> None:
        self.publishers = RosZenohPublishers(
            session, transport=self.transport, domain_id=self.domain_id,
            node_name=self.node_name, namespace=self.namespace)
        qos = _qos_by_topic()
        for topic, ros_type in TOPIC_TYPES.items():
            if self.stream.feed is None and ros_type != TF_MESSAGE_TYPE:
                continue
            self.publishers.advertise(topic, ros_type, qos[topic])
        self.sink = self.publishers.put
        self.stream.warm_up()
        log.info("simulated head on %s (domain %d): %s", self.transport, self.domain_id,
                 ", ".join(sorted(self.publishers.keys())))

    def tick(self, now_ns: int) -> Iterable[Outgoing]:
        if self.sink is None:
            return []
        messages = self.stream.due(now_ns)
        if any(m.ros_type == IMAGE_TYPE for m in messages):
            self.stats.latency("render", self.stream.render_ms * 1e-3)
            self.stats.latency("encode", self.stream.encode_ms * 1e-3)
            # a frame took time: the /tf stamps that came due meanwhile go out now
            messages += self.stream.due(time.time_ns() if self.publishers else now_ns)
        for message in messages:
            try:
                self.sink(message)
            except Exception:
                self.stats.count("publish_errors")
                log.exception("publishing %s failed", message.topic)
                continue
            self.stats.count(f"ros_{message.topic.rsplit('/', 1)[-1]}")
            self.stats.event(message.topic)
        return []

    def counters(self) -> dict[str, int]:
        out = super().counters()
        out["tf_skipped"] = self.stream.counters["tf_skipped"]
        feed = self.stream.feed
        if feed is not None:
            out["frames_skipped"] = int(feed.skipped)
        return out

    def state(self) -> tuple[str, str]:
        c = self.stream.counters
        detail = (f"simulated head on {self.transport}: tf={c['tf']} tf_static={c['tf_static']} "
                  f"frames={c['images']} render={self.stream.render_ms:.0f} ms "
                  f"encode={self.stream.encode_ms:.0f} ms")
        feed = self.stream.feed
        if feed is not None and feed.seq > 10 and feed.skipped > feed.seq:
            return "degraded", f"{detail}; rendering cannot keep up with --rate"
        if c["tf_skipped"] > self._skipped_seen:
            self._skipped_seen = c["tf_skipped"]
            self._skipped_at_s = time.monotonic()
        if self._skipped_at_s is not None and \
                time.monotonic() - self._skipped_at_s < RECENT_STALL_S:
            return "degraded", (f"{detail}; /tf stamps skipped after a stall "
                                f"({c['tf_skipped']} in all)")
        return "ok", detail

    def close(self) -> None:
        if self.publishers is not None:
            self.publishers.close()
            self.publishers = None
        feed = self.stream.feed
        if feed is not None:
            feed.release()
        super().close()


def build_parser() -> argparse.ArgumentParser:
    from simulation.live import add_sim_arguments

    parser = argparse.ArgumentParser(
        prog="smartedge sim-head", description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--rate", type=float, default=DEFAULT_RATE_HZ, metavar="HZ",
                        help=f"RGB-D frames per second (default {DEFAULT_RATE_HZ:g}; 0: /tf only)")
    parser.add_argument("--tf-rate", type=float, default=DEFAULT_TF_RATE_HZ, metavar="HZ",
                        help=f"/tf messages per second (default {DEFAULT_TF_RATE_HZ:g})")
    parser.add_argument("--still", action="store_true",
                        help="hold the head at pan = tilt = 0 (the site file's mounting)")
    parser.add_argument("--depth-sigma-per-m", type=float, metavar="K",
                        help="depth noise sigma_z = K z^2 (default: the simulation's, "
                        "0: exact depth)")
    parser.add_argument("--ros-transport", choices=TRANSPORTS, default="rmw_zenoh",
                        help="how ROS 2 reaches Zenoh (default rmw_zenoh)")
    parser.add_argument("--ros-domain-id", type=int, metavar="N",
                        help="ROS domain id (default: $ROS_DOMAIN_ID or 0)")
    parser.add_argument("--ros-namespace", default="", metavar="NS",
                        help="ROS namespace of the node (rmw_zenoh) or the bridge's namespace "
                        "(ros2dds); default none")
    parser.add_argument("--ros-node-name", default=DEFAULT_NODE_NAME,
                        help=f"ROS node name (default {DEFAULT_NODE_NAME})")
    add_session_arguments(parser)
    add_sim_arguments(parser)
    return parser


def build_node(args: argparse.Namespace) -> HeadRosNode:
    from robot_bridge.adapters.rmw_zenoh import resolve_domain_id
    from simulation.live import HeadCameraFeed, LiveSimulation, spec_from_args
    from simulation.site_cameras import DepthNoise

    if not (math.isfinite(args.rate) and args.rate >= 0.0):
        raise UsageError(f"--rate {args.rate}: must be >= 0")
    if not (math.isfinite(args.tf_rate) and args.tf_rate > 0.0):
        raise UsageError(f"--tf-rate {args.tf_rate}: must be > 0")
    live = LiveSimulation(spec_from_args(args))
    head_camera = live.site.robot_model(live.robot_id).head_camera
    if head_camera is None:
        raise UsageError(f"robot {live.robot_id!r} has no head_camera in "
                         f"{live.site.source_path} (robot_models.<model>.head_camera)")
    head = SimulatedHead.for_site_head(head_camera.T_base_cam, live.spec.epoch_ns,
                                       live.spec.seed, moving=not args.still)
    feed = None
    if args.rate > 0.0:
        depth_noise = None
        if args.depth_sigma_per_m is not None:
            try:
                depth_noise = DepthNoise(sigma_per_m=float(args.depth_sigma_per_m))
            except ValueError as exc:
                raise UsageError(f"--depth-sigma-per-m: {exc}") from None
        feed = HeadCameraFeed(live, rate_hz=args.rate, depth_noise=depth_noise, head=head)
    stream = HeadRosStream(head, feed, tf_rate_hz=args.tf_rate)
    domain_id = resolve_domain_id(args.ros_domain_id)
    log.info("%s: SIMULATED head (%s) %dx%d at %g Hz, /tf at %g Hz", live.robot_id,
             "still" if args.still else "looking around", head_camera.width, head_camera.height,
             args.rate, args.tf_rate)
    return HeadRosNode(live.site, live.robot_id, stream, transport=args.ros_transport,
                       domain_id=domain_id, node_name=args.ros_node_name,
                       namespace=args.ros_namespace)


def main(argv: Sequence[str]) -> int:
    return service_main("sim-head", argv, build_parser, build_node)
