"""Who may put what on the bus: the Zenoh ``access_control`` block of the site's router.

One identity per service, named by the common name (CN) of its TLS client certificate:

==================  =================================================================
``edge-<camera>``   an edge agent: its camera's detections, cloud, preview image,
                    status and liveliness token
``backend``         the backend host's services (backend, mapper, viewer): fused and
                    camera-only poses, the semantic map, their statuses and tokens, and
                    the backends' robot owner and area tokens
``bridge-<robot>``  a robot bridge: the robot's odometry, localization, corrections,
                    cloud, its status and token, and the ROS topics it drives on the
                    robot (corrections, pose outputs, tf)
``ros-<robot>``     the robot's ROS side (zenoh-bridge-ros2dds or rmw_zenoh's router):
                    only the robot's odometry and localization topics, nothing on the
                    site's keys
``viewer-<name>``   an extra viewer (a laptop): its own status and token
==================  =================================================================

Every identity but ``ros-<robot>`` may read (subscribe, query, watch liveliness) the whole site
prefix ``smartedge/<site>/**``; ``bridge-<robot>`` and ``ros-<robot>`` also read the robot's ROS
keys. Everything else is denied (``default_permission: "deny"``), including any peer whose
certificate names no identity of the site.

How the router applies the block (zenoh 1.x, checked with eclipse-zenoh 1.10.2): each message
crossing a link is matched against the rules of the subject of that link, in the direction it
crosses it. A put is checked *ingress* on the publisher's link (the ``put`` grant) and *egress*
on each subscriber's link (the read grant); a subscription is a ``declare_subscriber`` ingress;
a liveliness token a ``liveliness_token`` ingress (egress towards liveliness subscribers).
Messages of the router's own session (``smartedge router``, or the backend when it is the
router) cross no link and are not filtered.

Pure: no zenoh import. :func:`access_control` builds the block as a dict, :func:`render_json5`
writes it, :func:`put_table_markdown` documents it (docs/deployment.md holds its output).
"""

from __future__ import annotations

import dataclasses
import functools
import json
import logging
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, Final

from core.site import Site
from protocol import keys
from protocol.errors import ValidationError
from protocol.validation import check_id

log = logging.getLogger(__name__)

#: the message kinds of a zenoh 1.x ACL rule (``AclMessage`` of zenoh-config 1.10)
MESSAGES: Final = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
)
FLOWS: Final = ("ingress", "egress")

#: what a publisher sends on its link (ingress)
PUT_MESSAGES: Final = ("put", "delete")
#: what a reader sends on its link (ingress): subscriptions, queries, liveliness interest
READ_DECLARE_MESSAGES: Final = (
    "declare_subscriber", "query", "declare_liveliness_subscriber", "liveliness_query")
#: what the router delivers to a reader (egress): data, replies, liveliness tokens, and the
#: declarations that tell a publisher someone listens
READ_DELIVER_MESSAGES: Final = (
    "put", "delete", "reply", "liveliness_token", "declare_subscriber", "declare_queryable")

#: services of the backend host (``backend`` identity)
BACKEND_SERVICES: Final = ("backend", "mapper", "viewer")
EDGE_SERVICE: Final = "edge-agent"
BRIDGE_SERVICE: Final = "robot-bridge"
VIEWER_SERVICE: Final = "viewer"

#: ROS topics the robot bridge publishes on the robot: corrections (HSR, Nav2/AMCL), the pose
#: outputs, tf, the semantic map and its obstacle grid (robot_bridge/adapters/ros2.py)
DEFAULT_BRIDGE_ROS_TOPICS: Final = (
    "laser_2d_correct_pose", "initialpose", "smartedge/pose", "smartedge/camera_pose", "tf",
    "smartedge/semantic_map", "smartedge/obstacles")
#: ROS topics the robot's own side publishes that the bridge reads: odometry and localization
#: (HSR on ROS 2 and ROS 1, Nav2/AMCL)
DEFAULT_ROBOT_ROS_TOPICS: Final = ("switched_odom", "odom", "hsrb/odom", "amcl_pose", "global_pose")
#: liveliness tokens of the ROS graph: rmw_zenoh's (``@ros2_lv/<domain>/...``) and
#: zenoh-bridge-ros2dds's (``@/<zid>/@ros2_lv/...``)
DEFAULT_ROS_LIVELINESS: Final = ("@ros2_lv/**", "@/*/@ros2_lv/**")


def ros_topic_keys(
    topics: Iterable[str], namespace: str = "", *, domain_id: int | None = None,
    ros2dds: bool = True, rmw_zenoh: bool = True, ros1: bool = False,
) -> tuple[str, ...]:
    """Key expressions of ROS topics as the bridges route them: zenoh-bridge-ros2dds ``[ns/]t``,
    rmw_zenoh ``<domain>/[ns/]t/**`` (any type and hash; ``*`` for any domain when
    ``domain_id`` is ``None``), zenoh-plugin-ros1 ``*/*/[ns/]t`` (any type and md5).
    ``topics`` with or without a leading ``/``."""
    ns = str(namespace).strip().strip("/")
    domain = "*" if domain_id is None else str(int(domain_id))
    out: list[str] = []
    for topic in topics:
        name = str(topic).strip().strip("/")
        path = f"{ns}/{name}" if ns else name
        if not name or any(not c or c.startswith("@") or "*" in c for c in path.split("/")):
            raise ValidationError("ros_topic", f"invalid ROS topic {topic!r}")
        if ros2dds:
            out.append(path)
        if rmw_zenoh:
            out.append(f"{domain}/{path}/**")
        if ros1:
            out.append(f"*/*/{path}")
    return tuple(dict.fromkeys(out))


@dataclasses.dataclass(frozen=True)
class RosKeys:
    """The ROS side of one robot as key expressions. ``bridge``: keys only the robot's bridge
    may put (corrections, pose outputs, tf); ``robot``: keys only the robot's ROS side may put
    (odometry, localization); ``liveliness``: ROS graph tokens both may declare and watch."""

    bridge: tuple[str, ...]
    robot: tuple[str, ...]
    liveliness: tuple[str, ...] = DEFAULT_ROS_LIVELINESS

    @classmethod
    def default(cls, namespace: str = "", *, domain_id: int | None = None,
                ros1: bool = False) -> RosKeys:
        """The default topics (:data:`DEFAULT_BRIDGE_ROS_TOPICS`,
        :data:`DEFAULT_ROBOT_ROS_TOPICS`) under ``namespace``, for zenoh-bridge-ros2dds and
        rmw_zenoh (and zenoh-plugin-ros1 with ``ros1``)."""
        return cls(
            bridge=ros_topic_keys(DEFAULT_BRIDGE_ROS_TOPICS, namespace, domain_id=domain_id,
                                  ros1=ros1),
            robot=ros_topic_keys(DEFAULT_ROBOT_ROS_TOPICS, namespace, domain_id=domain_id,
                                 ros1=ros1),
        )

    @classmethod
    def from_section(cls, section: Mapping[str, Any], *, ros1: bool = False) -> RosKeys:
        """The default topics plus those a site file's ``ros`` section names (``namespace``,
        ``domain_id`` and the ``*_topic`` overrides of robot_bridge's ``RosConfig``); the
        section is validated by the bridge, this only reads it."""
        namespace = str(section.get("namespace") or "")
        try:
            domain_id = int(section.get("domain_id", 0))
        except (TypeError, ValueError):
            raise ValidationError("ros.domain_id", "expected an integer") from None
        bridge = [*DEFAULT_BRIDGE_ROS_TOPICS, *(
            str(section[k]) for k in ("correction_topic", "pose_topic", "camera_pose_topic",
                                      "tf_topic", "map_cloud_topic", "obstacles_topic")
            if section.get(k))]
        robot = [*DEFAULT_ROBOT_ROS_TOPICS, *(
            str(section[k]) for k in ("odometry_topic", "localization_topic")
            if section.get(k) and section.get(k) != "none")]
        return cls(
            bridge=ros_topic_keys(bridge, namespace, domain_id=domain_id, ros1=ros1),
            robot=ros_topic_keys(robot, namespace, domain_id=domain_id, ros1=ros1),
        )


def site_ros_keys(site: Site, *, ros1: bool = False) -> dict[str, RosKeys]:
    """Every robot's :class:`RosKeys` from the site file: the ``ros`` section with the robot
    entry's own ``ros:`` keys on top (:meth:`core.site.Site.ros_section`)."""
    return {rid: RosKeys.from_section(site.ros_section(rid), ros1=ros1) for rid in site.robots}


def ros_conflicts(ros_keys: Mapping[str, RosKeys]) -> list[str]:
    """Pairs of robots whose ROS sides share a topic key (two bridges would correct each
    other's robot, and one ACL right would cover both): one line per pair, naming both robots
    and the first shared key, empty when every robot has its own topics."""
    out = []
    robots = sorted(ros_keys)
    for i, a in enumerate(robots):
        keys_a = (*ros_keys[a].bridge, *ros_keys[a].robot)
        for b in robots[i + 1:]:
            keys_b = (*ros_keys[b].bridge, *ros_keys[b].robot)
            shared = next(((ka, kb) for ka in keys_a for kb in keys_b
                           if key_exprs_intersect(ka, kb)), None)
            if shared is not None:
                what = repr(shared[0]) if shared[0] == shared[1] else \
                    f"{shared[0]!r} and {shared[1]!r}"
                out.append(
                    f"robots {a!r} and {b!r} share ROS topics ({what}): give each robot its "
                    f"own ROS namespace or domain_id in its entry, e.g. "
                    f"`- {{id: {b}, model: ..., ros: {{namespace: /{b}}}}}`")
    return out


def _verbatim(chunk: str) -> bool:
    return chunk.startswith("@")


def _chunk_match(a: str, b: str) -> bool:
    if a == b:
        return True
    if _verbatim(a) or _verbatim(b):
        return False
    # "$*" inside a chunk is matched conservatively, as if it were "*"
    return a in ("*", "**") or b in ("*", "**") or "$*" in a or "$*" in b


def key_exprs_intersect(a: str, b: str) -> bool:
    """Whether two key expressions share a key (``*`` one chunk, ``**`` any number, chunks
    starting with ``@`` matched only verbatim; ``$*`` treated as ``*``, i.e. conservatively)."""
    ca, cb = a.split("/"), b.split("/")

    @functools.cache
    def meet(i: int, j: int) -> bool:
        if i == len(ca) and j == len(cb):
            return True
        if i < len(ca) and ca[i] == "**" and (
                meet(i + 1, j) or (j < len(cb) and not _verbatim(cb[j]) and meet(i, j + 1))):
            return True
        if j < len(cb) and cb[j] == "**" and (
                meet(i, j + 1) or (i < len(ca) and not _verbatim(ca[i]) and meet(i + 1, j))):
            return True
        return (i < len(ca) and j < len(cb) and _chunk_match(ca[i], cb[j])
                and meet(i + 1, j + 1))

    return meet(0, 0)


@dataclasses.dataclass(frozen=True)
class Grant:
    """What one identity may do. ``put``: key expressions it may put and delete on;
    ``tokens``: liveliness tokens it may declare; ``read``: key expressions it may subscribe to,
    query and watch, and be delivered. ``role``: ``edge``, ``backend``, ``bridge``, ``ros`` or
    ``viewer``; ``about``: the camera, robot or viewer it stands for (empty for the backend)."""

    identity: str
    role: str
    about: str
    put: tuple[str, ...]
    tokens: tuple[str, ...]
    read: tuple[str, ...]


def edge_identity(camera_id: str) -> str:
    """Certificate CN of the edge agent of ``camera_id``."""
    return f"edge-{check_id('camera_id', camera_id)}"


def bridge_identity(robot_id: str) -> str:
    """Certificate CN of the robot bridge of ``robot_id``."""
    return f"bridge-{check_id('robot_id', robot_id)}"


def ros_identity(robot_id: str) -> str:
    """Certificate CN of the ROS side (zenoh-bridge-ros2dds / rmw_zenoh router) of ``robot_id``."""
    return f"ros-{check_id('robot_id', robot_id)}"


def viewer_identity(name: str) -> str:
    """Certificate CN of an extra viewer ``name`` (a laptop)."""
    return f"viewer-{check_id('viewer', name)}"


BACKEND_IDENTITY: Final = "backend"


def _site_prefix(site: str) -> str:
    return f"{keys.ROOT}/{check_id('site', site)}/**"


def _ros_keys_for(robot_id: str, ros_keys: RosKeys | Mapping[str, RosKeys] | None) -> RosKeys:
    if ros_keys is None:
        return RosKeys.default()
    if isinstance(ros_keys, RosKeys):
        return ros_keys
    return ros_keys.get(robot_id) or RosKeys.default()


def grants(
    site: Site,
    ros_keys: RosKeys | Mapping[str, RosKeys] | None = None,
    viewers: Sequence[str] = (),
) -> list[Grant]:
    """One :class:`Grant` per identity of ``site``: its cameras, the backend, one bridge and one
    ROS side per robot, and the extra ``viewers``. ``ros_keys``: the robots' ROS keys, one set
    for all or by robot id (default :meth:`RosKeys.default`, no namespace)."""
    s = site.name
    prefix = _site_prefix(s)
    out: list[Grant] = []
    for cam in sorted(site.cameras):
        out.append(Grant(
            edge_identity(cam), "edge", cam,
            put=(keys.detections_key(s, cam), keys.edge_cloud_key(s, cam), keys.image_key(s, cam),
                 keys.status_key(s, EDGE_SERVICE, cam)),
            tokens=(keys.alive_key(s, EDGE_SERVICE, cam),),
            read=(prefix,),
        ))  # fmt: skip
    out.append(Grant(
        BACKEND_IDENTITY, "backend", "",
        put=(keys.pose_key(s, "*"), keys.camera_pose_key(s, "*"), keys.map_voxels_key(s, "*"),
             *(keys.status_key(s, svc, "*") for svc in BACKEND_SERVICES)),
        tokens=(*(keys.alive_key(s, svc, "*") for svc in BACKEND_SERVICES),
                keys.owner_key(s, "*", "*"), keys.area_key(s, "*", "*")),
        read=(prefix,),
    ))  # fmt: skip
    if isinstance(ros_keys, Mapping) and len(site.robots) > 1:
        conflicts = ros_conflicts({r: _ros_keys_for(r, ros_keys) for r in site.robots})
        if conflicts:
            raise ValidationError("ros_keys", "; ".join(conflicts))
    for robot in sorted(site.robots):
        ros = _ros_keys_for(robot, ros_keys)
        for key in (*ros.bridge, *ros.robot):
            if key_exprs_intersect(key, prefix):
                raise ValidationError(
                    "ros_keys", f"ROS key {key!r} of robot {robot!r} overlaps the site's keys "
                    f"{prefix!r}: give the ROS domain or a namespace")
        out.append(Grant(
            bridge_identity(robot), "bridge", robot,
            put=(keys.odom_key(s, robot), keys.localization_key(s, robot),
                 keys.correction_key(s, robot), keys.robot_cloud_key(s, robot),
                 keys.status_key(s, BRIDGE_SERVICE, robot), *ros.bridge),
            tokens=(keys.alive_key(s, BRIDGE_SERVICE, robot), *ros.liveliness),
            read=(prefix, *ros.robot, *ros.liveliness),
        ))  # fmt: skip
        out.append(Grant(
            ros_identity(robot), "ros", robot,
            put=ros.robot,
            tokens=ros.liveliness,
            read=(*ros.bridge, *ros.liveliness),
        ))  # fmt: skip
    for name in viewers:
        out.append(Grant(
            viewer_identity(name), "viewer", name,
            put=(keys.status_key(s, VIEWER_SERVICE, name),),
            tokens=(keys.alive_key(s, VIEWER_SERVICE, name),),
            read=(prefix,),
        ))  # fmt: skip
    seen: set[str] = set()
    for grant in out:
        if grant.identity in seen:
            raise ValidationError("identity", f"{grant.identity!r} twice (robot and viewer ids "
                                  "must give distinct certificate names)")
        seen.add(grant.identity)
    return out


def identities(site: Site, viewers: Sequence[str] = ()) -> list[str]:
    """The certificate common names of ``site``, in :func:`grants` order."""
    return [g.identity for g in grants(site, viewers=viewers)]


def _rule(rule_id: str, messages: Sequence[str], flows: Sequence[str],
          key_exprs: Sequence[str]) -> dict[str, Any]:
    return {"id": rule_id, "messages": list(messages), "flows": list(flows),
            "permission": "allow", "key_exprs": list(dict.fromkeys(key_exprs))}


def _covers(wide: str, key: str) -> bool:
    """``wide`` (``prefix/**``) includes ``key`` (no verbatim chunk below the prefix)."""
    if not wide.endswith("/**"):
        return wide == key
    stem = wide[:-2]
    return key.startswith(stem) and not any(c.startswith("@") for c in key[len(stem):].split("/"))


def rules_of(grant: Grant) -> list[dict[str, Any]]:
    """The allow rules of one identity (rule ids ``<identity>/<what>``)."""
    i = grant.identity
    rules = []
    if grant.put:
        rules.append(_rule(f"{i}/put", PUT_MESSAGES, ["ingress"], grant.put))
    if grant.tokens:
        rules.append(_rule(f"{i}/tokens", ["liveliness_token"], ["ingress"], grant.tokens))
    if grant.read:
        rules.append(_rule(f"{i}/read", READ_DECLARE_MESSAGES, ["ingress"], grant.read))
    # delivered: what it reads, and the subscriptions to what it puts (so that a client's
    # publisher learns someone listens)
    deliver = [k for k in (*grant.put, *grant.tokens)
               if not any(_covers(r, k) for r in grant.read)]
    deliver = [*grant.read, *deliver]
    if deliver:
        rules.append(_rule(f"{i}/deliver", READ_DELIVER_MESSAGES, ["egress"], deliver))
    return rules


def access_control(
    site: Site,
    ros_keys: RosKeys | Mapping[str, RosKeys] | None = None,
    viewers: Sequence[str] = (),
) -> dict[str, Any]:
    """The ``access_control`` block of the site's router (zenoh 1.x schema): default deny, one
    subject per identity matched by ``cert_common_names``, one policy joining it to its rules.
    Arguments as :func:`grants`."""
    all_grants = grants(site, ros_keys, viewers)
    rules: list[dict[str, Any]] = []
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for grant in all_grants:
        own = rules_of(grant)
        rules.extend(own)
        subjects.append({"id": grant.identity, "cert_common_names": [grant.identity]})
        policies.append({"id": grant.identity, "rules": [r["id"] for r in own],
                         "subjects": [grant.identity]})
    log.debug("access control for site %s: %d identities, %d rules", site.name,
              len(all_grants), len(rules))
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }


def render_json5(block: Any, indent: int = 2, _level: int = 0) -> str:
    """``block`` as json5 text, e.g. for ``access_control: <text>``: strict JSON (which is
    json5), objects one member a line, lists of plain values on one line."""
    pad, inner = " " * (indent * _level), " " * (indent * (_level + 1))
    if isinstance(block, Mapping):
        if not block:
            return "{}"
        members = [f"{inner}{json.dumps(str(k))}: {render_json5(v, indent, _level + 1)}"
                   for k, v in block.items()]
        return "{\n" + ",\n".join(members) + f"\n{pad}}}"
    if isinstance(block, (list, tuple)):
        if all(not isinstance(v, (Mapping, list, tuple)) for v in block):
            return json.dumps(list(block))
        items = [f"{inner}{render_json5(v, indent, _level + 1)}" for v in block]
        return "[\n" + ",\n".join(items) + f"\n{pad}]"
    return json.dumps(block)


def access_control_json5(
    site: Site,
    ros_keys: RosKeys | Mapping[str, RosKeys] | None = None,
    viewers: Sequence[str] = (),
) -> str:
    """:func:`access_control` rendered by :func:`render_json5`."""
    return render_json5(access_control(site, ros_keys, viewers))


def _code(items: Iterable[str]) -> str:
    return ", ".join(f"`{item}`" for item in items) or "nothing"


def put_table_markdown(
    site: Site,
    ros_keys: RosKeys | Mapping[str, RosKeys] | None = None,
    viewers: Sequence[str] = (),
) -> str:
    """A Markdown table: each identity of ``site``, the keys it may put and the liveliness
    tokens it may declare (what docs/deployment.md shows for the example site)."""
    lines = ["| identity (certificate CN) | may put | liveliness tokens | reads |",
             "|---|---|---|---|"]
    prefix = _site_prefix(site.name)
    for grant in grants(site, ros_keys, viewers):
        site_read = prefix in grant.read
        others = [k for k in grant.read if k != prefix and k not in grant.tokens]
        read = ("the site" if site_read else "") + (
            (" and " if site_read else "") + "the robot's ROS keys" if others else "")
        lines.append(f"| `{grant.identity}` | {_code(grant.put)} | {_code(grant.tokens)} | "
                     f"{read or 'nothing'} |")
    return "\n".join(lines) + "\n"
