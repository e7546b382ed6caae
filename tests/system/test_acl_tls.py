"""Identity and authorization on the bus, over real Zenoh on loopback: certificates and router
config made by ``smartedge certs``, a router with the generated ``access_control`` block, and
clients holding the edge, backend, bridge and ROS-side certificates (issue 17, item 1)."""

from __future__ import annotations

import json
import shutil
import time
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest

from protocol import keys
from tests.conftest import EXAMPLE_SITE, free_port, wait_until

zenoh = pytest.importorskip("zenoh")
pytestmark = pytest.mark.skipif(shutil.which("openssl") is None, reason="openssl not installed")

SITE = "lab"  # the example site's name
ROS_CORRECTION = "laser_2d_correct_pose"
ROS_ODOM = "switched_odom"
SETTLE_S = 0.3


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """``smartedge certs`` on the example site, the configs pointing at the output directory."""
    from smartedge.cli import main

    out = tmp_path_factory.mktemp("pki")
    rc = main(["certs", "--site", str(EXAMPLE_SITE), "--out", str(out), "--router-host",
               "backend.lab", "--tls-dir", str(out), "--days", "2"])  # fmt: skip
    assert rc == 0
    return out


class Bus:
    """A router on the generated config and client sessions by identity."""

    def __init__(self, pki: Path) -> None:
        self.pki = pki
        self.port = free_port()
        conf = zenoh.Config.from_file(str(pki / "router-acl.json5"))
        conf.insert_json5("listen/endpoints", json.dumps([f"tls/127.0.0.1:{self.port}"]))
        self.router = zenoh.open(conf)
        self.sessions: list[Any] = []

    def client(self, identity: str) -> Any:
        conf = zenoh.Config.from_file(str(self.pki / "clients" / f"{identity}.json5"))
        conf.insert_json5("connect/endpoints", json.dumps([f"tls/localhost:{self.port}"]))
        session = zenoh.open(conf)
        self.sessions.append(session)
        return session

    def close(self) -> None:
        for session in reversed(self.sessions):
            session.close()
        self.router.close()


@pytest.fixture
def bus(pki: Path) -> Iterator[Bus]:
    b = Bus(pki)
    try:
        yield b
    finally:
        b.close()


def _collect(session: Any, key_expr: str) -> tuple[Any, list[tuple[str, bytes]]]:
    """A subscriber on ``key_expr`` and the (key, payload) pairs it receives."""
    got: list[tuple[str, bytes]] = []
    sub = session.declare_subscriber(
        key_expr, lambda s: got.append((str(s.key_expr), s.payload.to_bytes())))
    return sub, got


def test_edge_identity_puts_only_its_own_keys(bus: Bus) -> None:
    backend = bus.client("backend")
    ros = bus.client("ros-hsr")
    bridge = bus.client("bridge-hsr")
    edge = bus.client("edge-cam_sw")
    _site_sub, site_got = _collect(backend, f"{keys.ROOT}/{SITE}/**")
    _ros_sub, ros_got = _collect(ros, ROS_CORRECTION)

    own = keys.detections_key(SITE, "cam_sw")
    forbidden = [keys.pose_key(SITE, "hsr"), keys.correction_key(SITE, "hsr"),
                 keys.camera_pose_key(SITE, "hsr"), keys.detections_key(SITE, "cam_se"),
                 keys.odom_key(SITE, "hsr"), ROS_CORRECTION]  # fmt: skip
    pubs = {k: edge.declare_publisher(k) for k in (*forbidden, own)}

    def round_trip() -> bool:
        for key in (*forbidden, own):  # the denied ones first, in order on one link
            pubs[key].put(b"edge")
        bridge.put(ROS_CORRECTION, b"bridge")  # the genuine one: proves the ROS side listens
        return (own, b"edge") in site_got and (ROS_CORRECTION, b"bridge") in ros_got

    assert wait_until(round_trip, timeout_s=5.0, step_s=0.1), (site_got, ros_got)
    time.sleep(SETTLE_S)
    assert {key for key, _ in site_got} == {own}, site_got
    assert {payload for _, payload in ros_got} == {b"bridge"}, ros_got


def test_backend_bridge_and_ros_identities_reach_their_consumers(bus: Bus) -> None:
    bridge = bus.client("bridge-hsr")
    ros = bus.client("ros-hsr")
    backend = bus.client("backend")
    watcher = bus.client("backend")  # another session: no local delivery of backend's puts
    _pose_sub, pose_got = _collect(bridge, keys.pose_key(SITE, "hsr"))
    _corr_sub, corr_got = _collect(ros, ROS_CORRECTION)
    _odom_sub, odom_got = _collect(bridge, ROS_ODOM)
    _site_sub, site_got = _collect(watcher, f"{keys.ROOT}/{SITE}/**")

    # the robot's ROS side: its odometry reaches the bridge, nothing it puts reaches the site
    def ros_round_trip() -> bool:
        ros.put(keys.odom_key(SITE, "hsr"), b"o")
        ros.put(keys.pose_key(SITE, "hsr"), b"o")
        ros.put(ROS_ODOM, b"o")
        return bool(odom_got)

    assert wait_until(ros_round_trip, timeout_s=5.0, step_s=0.1), "ROS odometry not delivered"
    time.sleep(SETTLE_S)
    assert site_got == [] and pose_got == []

    assert wait_until(lambda: (backend.put(keys.pose_key(SITE, "hsr"), b"p"), bool(pose_got))[1],
                      timeout_s=5.0, step_s=0.1), "the backend's pose was not delivered"
    assert wait_until(lambda: (bridge.put(ROS_CORRECTION, b"c"), bool(corr_got))[1],
                      timeout_s=5.0, step_s=0.1), "the bridge's correction was not delivered"
    assert wait_until(lambda: (keys.pose_key(SITE, "hsr"), b"p") in site_got, timeout_s=5.0)


def test_liveliness_tokens_only_on_own_alive_key(bus: Bus) -> None:
    """The runtime's pattern: a token per service, liveliness subscribers with history."""
    backend = bus.client("backend")
    edge = bus.client("edge-cam_sw")
    bridge = bus.client("bridge-hsr")
    seen: list[tuple[str, bool]] = []

    def on_token(sample: Any, _seen: list[tuple[str, bool]] = seen) -> None:
        _seen.append((str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT))

    backend.liveliness().declare_subscriber(keys.alive_key(SITE, "*", "*"), on_token)
    time.sleep(SETTLE_S)
    edge_alive = keys.alive_key(SITE, "edge-agent", "cam_sw")
    backend_alive = keys.alive_key(SITE, "backend", "main")
    foreign = edge.liveliness().declare_token(backend_alive)
    own = edge.liveliness().declare_token(edge_alive)
    assert wait_until(lambda: (edge_alive, True) in seen, timeout_s=5.0)
    time.sleep(SETTLE_S)
    assert backend_alive not in {key for key, _ in seen}

    # a late subscriber with history (the bridge watching the backend) sees the genuine token
    genuine = backend.liveliness().declare_token(backend_alive)
    history: list[tuple[str, bool]] = []
    bridge.liveliness().declare_subscriber(
        keys.alive_key(SITE, "*", "*"), lambda s: history.append((str(s.key_expr), True)),
        history=True)
    assert wait_until(lambda: {(edge_alive, True), (backend_alive, True)} <= set(history),
                      timeout_s=5.0), history
    own.undeclare()
    assert wait_until(lambda: (edge_alive, False) in seen, timeout_s=5.0)
    foreign.undeclare()
    genuine.undeclare()


def test_unknown_certificate_name_gets_nothing(bus: Bus, pki: Path, tmp_path: Path) -> None:
    """A CA-signed certificate whose CN names no identity joins but can neither put nor read."""
    from smartedge.commands.certs import _issue, _new_key

    work = tmp_path / "rogue"
    work.mkdir()
    for name in ("ca.crt", "ca.key"):
        shutil.copy(pki / name, work / name)
    _new_key(work / "edge-cam_zz.key")
    _issue(work, "edge-cam_zz", 2, "extendedKeyUsage=clientAuth\n")
    text = (pki / "clients" / "edge-cam_sw.json5").read_text()
    text = text.replace(f"{pki}/edge-cam_sw.", f"{work}/edge-cam_zz.")
    (work / "client.json5").write_text(text)
    conf = zenoh.Config.from_file(str(work / "client.json5"))
    conf.insert_json5("connect/endpoints", json.dumps([f"tls/localhost:{bus.port}"]))
    rogue = zenoh.open(conf)
    bus.sessions.append(rogue)
    backend = bus.client("backend")
    edge = bus.client("edge-cam_sw")
    _site_sub, site_got = _collect(backend, f"{keys.ROOT}/{SITE}/**")
    _rogue_sub, rogue_got = _collect(rogue, f"{keys.ROOT}/{SITE}/**")
    own = keys.detections_key(SITE, "cam_sw")

    def round_trip() -> bool:
        rogue.put(keys.pose_key(SITE, "hsr"), b"r")
        rogue.put(keys.detections_key(SITE, "cam_zz"), b"r")
        edge.put(own, b"x")
        return (own, b"x") in site_got

    assert wait_until(round_trip, timeout_s=5.0, step_s=0.1)
    time.sleep(SETTLE_S)
    assert {key for key, _ in site_got} == {own}
    assert (own, b"x") not in rogue_got  # it only hears its own puts, delivered inside its session


# --------------------------------------------------------------------------------------------
# smartedge certs itself
# --------------------------------------------------------------------------------------------


def _certs(out: Path, *extra: str) -> int:
    from smartedge.cli import main

    return main(["certs", "--site", str(EXAMPLE_SITE), "--out", str(out), "--days", "2", *extra])


def test_certs_keeps_keys_and_issues_again_only_what_changed(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    import stat

    out = tmp_path / "pki"
    assert _certs(out, "--router-host", "backend.lab") == 0
    first = capsys.readouterr().out
    assert "CA: created" in first and "edge-cam_sw: new key and certificate" in first
    assert stat.S_IMODE(out.stat().st_mode) == 0o700
    keys_before = {p.name: p.read_bytes() for p in out.glob("*.key")}
    assert set(keys_before) >= {"ca.key", "router.key", "backend.key", "bridge-hsr.key",
                                "ros-hsr.key", "edge-cam_sw.key"}  # fmt: skip
    assert all(stat.S_IMODE((out / k).stat().st_mode) == 0o600 for k in keys_before)

    assert _certs(out, "--router-host", "backend.lab") == 0
    again = capsys.readouterr().out
    assert "CA: using the existing" in again and "new key" not in again
    assert "edge-cam_sw: kept" in again and "router: kept" in again

    # a new router address: the router's certificate again, from the same key
    router_crt = (out / "router.crt").read_bytes()
    assert _certs(out, "--router-host", "backend.lab", "--router-host", "10.0.0.9") == 0
    assert "router: certificate issued again from the existing key (subjectAltName lacks " \
           "IP:10.0.0.9)" in capsys.readouterr().out
    assert (out / "router.crt").read_bytes() != router_crt
    assert {p.name: p.read_bytes() for p in out.glob("*.key")} == keys_before

    # a new CA (the old one removed): every certificate again, keys kept
    (out / "ca.key").unlink()
    (out / "ca.crt").unlink()
    assert _certs(out) == 0
    text = capsys.readouterr().out
    assert "edge-cam_sw: certificate issued again from the existing key (does not verify" in text
    assert (out / "edge-cam_sw.key").read_bytes() == keys_before["edge-cam_sw.key"]

    assert _certs(out, "--force") == 0
    assert (out / "edge-cam_sw.key").read_bytes() != keys_before["edge-cam_sw.key"]
    router = zenoh.Config.from_file(str(out / "router-acl.json5"))
    assert json.loads(router.get_json("access_control/default_permission")) == "deny"


def test_certs_errors_are_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str],
                                   monkeypatch: pytest.MonkeyPatch) -> None:
    out = tmp_path / "pki"
    out.mkdir()
    (out / "ca.crt").write_text("orphan")
    assert _certs(out) == 1
    assert "only one of ca.key and ca.crt" in capsys.readouterr().err
    assert _certs(tmp_path / "x", "--router-host", "bad host") == 1
    assert "not a host name" in capsys.readouterr().err
    monkeypatch.setattr(shutil, "which", lambda name: None)
    assert _certs(tmp_path / "y") == 1
    assert "openssl command is not installed" in capsys.readouterr().err
