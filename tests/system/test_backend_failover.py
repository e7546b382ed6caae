"""A backend killed during a three-backend run (issue 30, item 4): its robots' estimates resume
from the others within 3 s, and never do two backends publish one robot, as seen on the bus.
The last test does it with three real ``smartedge backend`` processes on the simulated site.

Real parts: ``smartedge router`` on a loopback port, three backends (two
:class:`~tests.system.ownership_probe.OwnershipProbe` runners in this process, one in a
subprocess that gets SIGKILL), each on its own client session with the runner's liveliness
token, and a monitor session that records, in arrival order, every owner token change and every
estimate with the backend named in its flags. The probes are the ownership half of the backend
(backend_service/ownership.py on :class:`~core.runtime.ZenohRunner`), without a pipeline.
"""

from __future__ import annotations

import bisect
import collections
import contextlib
import dataclasses
import itertools
import json
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator, Sequence
from pathlib import Path
from typing import Any

import pytest

from backend_service.ownership import choose_owner, parse_liveliness
from core.runtime import ZenohRunner
from lab.launcher import start_service
from protocol import decode, encode, keys
from protocol.messages import NS_PER_S, Odometry, PoseEstimate, RobotDetections
from tests.conftest import REPO_ROOT, free_port, stop_process, wait_until
from tests.system.ownership_probe import FLAG_PREFIX, OwnershipProbe

zenoh = pytest.importorskip("zenoh")

# exclusive: real-time ownership on a 2-core machine. In one parallel run (2026-12-08, another
# worker's tests beside it) the frozen-backend test's monitor saw b2 take over four robots whose
# b1 owner tokens it still saw standing: their deletions reached the monitor 1.5 s after b2's
# first poses, the other two at once. Not seen alone on the machine; not yet explained (is it
# the monitor's delivery or b2 claiming early?): the closing note of that session says so.
pytestmark = [pytest.mark.slow, pytest.mark.exclusive]

SITE = "lab"
ROBOTS = tuple(f"robot_{i}" for i in range(6))
INSTANCES = ("b1", "b2", "b3")
ROUTER_CONFIG = REPO_ROOT / "deploy" / "zenoh" / "router.json5"
#: the issue's target: robots resume within this after their backend died
FAILOVER_TARGET_S = 3.0


def client_config(endpoint: str) -> Any:
    doc = {"mode": "client", "connect": {"endpoints": [endpoint]},
           "scouting": {"multicast": {"enabled": False}}}
    return zenoh.Config.from_json5(json.dumps(doc))


@dataclasses.dataclass
class BusMonitor:
    """What a session on the router saw, in arrival order: ``("token", t_ns, robot, instance,
    present)`` and ``("pose", t_ns, robot, instance, stamp_ns)`` (``t_ns``: arrival)."""

    events: list[tuple[Any, ...]] = dataclasses.field(default_factory=list)
    lock: threading.Lock = dataclasses.field(default_factory=threading.Lock)

    def on_token(self, sample: Any) -> None:
        parsed = parse_liveliness(str(sample.key_expr))
        assert parsed is not None and parsed[1] == "owner", str(sample.key_expr)
        with self.lock:
            self.events.append(("token", time.time_ns(), parsed[2], parsed[3],
                                sample.kind == zenoh.SampleKind.PUT))

    def on_pose(self, sample: Any) -> None:
        est = decode(sample.payload.to_bytes(), expected=PoseEstimate)
        by = [f[len(FLAG_PREFIX):] for f in est.flags if f.startswith(FLAG_PREFIX)]
        with self.lock:
            self.events.append(("pose", time.time_ns(), est.robot_id, by[0] if by else "?",
                                est.stamp_ns))

    def snapshot(self) -> list[tuple[Any, ...]]:
        with self.lock:
            return list(self.events)

    def last_publishers(self) -> dict[str, str]:
        out: dict[str, str] = {}
        for ev in self.snapshot():
            if ev[0] == "pose":
                out[ev[2]] = ev[3]
        return out


#: two estimates of one backend at most this far apart (stamps) count as one run of publishing
#: (the probes publish every 20 ms)
RUN_GAP_NS = 100_000_000


def check_exclusive(events: list[tuple[Any, ...]]) -> list[str]:
    """Violations of exclusive publishing in ``events`` (an estimate's time is its stamp: the
    publisher's clock, this machine's; a token's, its arrival at the monitor):

    - an estimate produced while its backend's owner token of the robot was not on the bus;
    - an estimate of one backend inside a run of another's (two publishing at once);
    - a handover, the first estimate of the new publisher, before the previous publisher's
      token had vanished (it stops, then undeclares; the next one claims after seeing that).

    A token alone does not make a publisher: a frozen backend's session re-declares its tokens
    when it reconnects, and the other backend goes on publishing until it has seen them."""
    spans: dict[tuple[str, str], list[list[int | None]]] = collections.defaultdict(list)
    poses: dict[str, list[tuple[int, str]]] = collections.defaultdict(list)
    for ev in events:
        if ev[0] == "token":
            _, t_ns, robot, inst, present = ev
            own = spans[(robot, inst)]
            if present and (not own or own[-1][1] is not None):
                own.append([t_ns, None])
            elif not present and own and own[-1][1] is None:
                own[-1][1] = t_ns
        else:
            poses[ev[2]].append((ev[4] if len(ev) > 4 else ev[1], ev[3]))

    def held(robot: str, inst: str, t_ns: int) -> bool:
        return any(a <= t_ns and (b is None or t_ns <= b) for a, b in spans.get((robot, inst), ()))

    problems = []
    for robot, seen in sorted(poses.items()):
        seen.sort()
        stamps_of: dict[str, list[int]] = collections.defaultdict(list)
        for stamp_ns, inst in seen:
            stamps_of[inst].append(stamp_ns)
        last: dict[str, int] = {}  # backend -> its latest estimate so far
        prev = None
        for stamp_ns, inst in seen:
            if not held(robot, inst, stamp_ns):
                problems.append(f"{robot}: estimate from {inst} without its owner token at "
                                f"{stamp_ns}")
            for other, t_ns in last.items():
                theirs = stamps_of[other]
                k = bisect.bisect_right(theirs, stamp_ns)
                nxt = theirs[k] if k < len(theirs) else None
                if other != inst and nxt is not None and nxt - t_ns <= RUN_GAP_NS:
                    problems.append(f"{robot}: {inst} published at {stamp_ns} while {other} "
                                    f"was publishing")
            if prev is not None and prev != inst and held(robot, prev, stamp_ns):
                problems.append(f"{robot}: {inst} took over at {stamp_ns} while {prev}'s token "
                                f"stood")
            last[inst] = stamp_ns
            prev = inst
    return problems


@contextlib.contextmanager
def smartedge_router(log_dir: Path, connect: Sequence[str] = ()) -> Iterator[str]:
    """``smartedge router`` on a free loopback port (connected to the ``connect`` routers),
    listening; yields its endpoint, stops it with SIGTERM (exit 0)."""
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    proc = start_service(
        ["router", "--config", str(ROUTER_CONFIG), "--listen", endpoint,
         *(a for e in connect for a in ("--connect", e))],
        log_dir / f"router-{port}.log", cwd=REPO_ROOT)
    try:
        proc.wait_listening(port, timeout_s=30.0)
        yield endpoint
    finally:
        assert proc.stop() == 0, proc.log_tail()


@pytest.fixture
def router(tmp_path: Path) -> Iterator[str]:
    with smartedge_router(tmp_path) as endpoint:
        yield endpoint


@pytest.fixture(params=[1, 2], ids=["one_router", "two_routers"])
def routers(request: pytest.FixtureRequest, tmp_path: Path) -> Iterator[tuple[str, str]]:
    """(a, b): one router twice, or two routers, b connected to a (a facility's areas)."""
    with smartedge_router(tmp_path) as a:
        if request.param == 1:
            yield a, a
            return
        with smartedge_router(tmp_path, connect=[a]) as b:
            yield a, b


def test_a_killed_backend_s_robots_resume_from_the_others_within_3_s(
        routers: tuple[str, str], tmp_path: Path) -> None:
    """On two routers, the monitor and one survivor use router a, the victim and the other
    survivor router b: the tokens cross the routers' link."""
    router_a, router_b = routers
    three = {r: choose_owner(r, INSTANCES) for r in ROBOTS}
    victim = three[ROBOTS[0]]
    survivors = tuple(i for i in INSTANCES if i != victim)
    two = {r: choose_owner(r, survivors) for r in ROBOTS}
    orphans = [r for r in ROBOTS if three[r] == victim]

    monitor = BusMonitor()
    session = zenoh.open(client_config(router_a))
    subs = [session.liveliness().declare_subscriber(keys.owner_key(SITE, "*", "*"),
                                                    monitor.on_token, history=True),
            session.declare_subscriber(keys.pose_key(SITE, "*"), monitor.on_pose)]
    log = tmp_path / "victim.log"
    proc = subprocess.Popen(
        [sys.executable, "-m", "tests.system.ownership_probe", "--site", SITE, "--id", victim,
         "--robots", ",".join(ROBOTS), "--mode", "client", "--connect", router_b,
         "--no-multicast-scouting"], cwd=REPO_ROOT, stdout=log.open("w"),
        stderr=subprocess.STDOUT)
    runners = [ZenohRunner(OwnershipProbe(SITE, inst, ROBOTS), client_config(endpoint))
               for inst, endpoint in zip(survivors, (router_a, router_b), strict=True)]
    threads = [threading.Thread(target=r.run, name=f"probe-{r.node.instance_id}", daemon=True)
               for r in runners]
    try:
        for thread in threads:
            thread.start()
        assert wait_until(lambda: monitor.last_publishers() == three, 30.0, 0.05), (
            monitor.last_publishers(), three, log.read_text()[-3000:])
        time.sleep(1.0)  # a steady run: everyone publishes its share
        kill_ns = time.time_ns()
        proc.kill()
        proc.wait(10)
        assert wait_until(lambda: monitor.last_publishers() == two, 2 * FAILOVER_TARGET_S,
                          0.02), (monitor.last_publishers(), two)
        time.sleep(0.5)
    finally:
        for runner in runners:
            runner.stop()
        for thread in threads:
            thread.join(10)
        if proc.poll() is None:
            proc.kill()
        for sub in subs:
            sub.undeclare()
        session.close()

    events = monitor.snapshot()
    problems = check_exclusive(events)
    trace = tmp_path / "bus.txt"
    trace.write_text("\n".join(" ".join(map(str, ev)) for ev in events))
    assert problems == [], (problems[:5], str(trace))
    token_lost_ms = min(ev[1] - kill_ns for ev in events if ev[0] == "token" and ev[1] > kill_ns
                        and ev[3] == victim and not ev[4]) / 1e6
    resume_ms = {r: min(ev[1] - kill_ns for ev in events if ev[0] == "pose" and ev[2] == r
                        and ev[1] > kill_ns and ev[3] == two[r]) / 1e6 for r in orphans}
    last_victim_ms = max((ev[1] - kill_ns for ev in events if ev[0] == "pose"
                          and ev[3] == victim), default=-1) / 1e6
    print(f"failover ({'one router' if router_a == router_b else 'two routers'}): victim "
          f"{victim} owned {orphans}; its owner tokens vanished "
          f"{token_lost_ms:.1f} ms after SIGKILL; robots resumed after "
          + ", ".join(f"{r} {ms:.0f} ms" for r, ms in resume_ms.items())
          + f"; its last estimate arrived {last_victim_ms:.1f} ms after the kill")
    assert max(resume_ms.values()) <= FAILOVER_TARGET_S * 1e3
    assert token_lost_ms < max(resume_ms.values())
    # the survivors never paused their own robots
    for robot in (r for r in ROBOTS if three[r] != victim):
        by = [ev[3] for ev in events if ev[0] == "pose" and ev[2] == robot and ev[1] > kill_ns]
        assert set(by) == {three[robot]}
    for runner in runners:
        counters = runner.node.table.counters
        assert counters["ownership.member_left"] == 1
    assert sum(r.node.table.counters["ownership.takeovers"] for r in runners) >= len(orphans)


def test_the_bus_check_sees_two_publishers_an_early_handover_and_a_missing_token() -> None:
    ms = 1_000_000
    ok = [("token", 1 * ms, "robot_0", "b1", True), ("pose", 0, "robot_0", "b1", 2 * ms),
          ("pose", 0, "robot_0", "b1", 22 * ms), ("token", 30 * ms, "robot_0", "b1", False),
          ("token", 40 * ms, "robot_0", "b2", True), ("pose", 0, "robot_0", "b2", 250 * ms)]
    assert check_exclusive(ok) == []
    early = [*ok[:3], ("token", 24 * ms, "robot_0", "b2", True),
             ("pose", 0, "robot_0", "b2", 25 * ms), ok[3]]
    assert check_exclusive(early) == ["robot_0: b2 took over at 25000000 while b1's token stood"]
    both = [*ok, ("token", 45 * ms, "robot_0", "b1", True),
            ("pose", 0, "robot_0", "b1", 240 * ms), ("pose", 0, "robot_0", "b1", 260 * ms)]
    assert "robot_0: b2 published at 250000000 while b1 was publishing" in check_exclusive(both)
    assert check_exclusive([("pose", 0, "robot_1", "b1", 1)]) == [
        "robot_1: estimate from b1 without its owner token at 1"]
    # a token re-declared by a reconnecting session makes no publisher: b1 goes on until it
    # has seen it, then withdraws; b2 takes over after b1's token vanished
    thaw = [*ok[:3], ("token", 23 * ms, "robot_0", "b2", True),
            ("pose", 0, "robot_0", "b1", 24 * ms), ("token", 30 * ms, "robot_0", "b1", False),
            ("pose", 0, "robot_0", "b2", 230 * ms)]
    assert check_exclusive(thaw) == []


def test_backends_started_at_once_settle_without_two_publishers(
        router: str, tmp_path: Path) -> None:
    """No join delay and a simultaneous start: each backend may claim every robot before it
    sees the other; the tie rule must settle it with one publisher per robot on the bus."""
    monitor = BusMonitor()
    session = zenoh.open(client_config(router))
    subs = [session.liveliness().declare_subscriber(keys.owner_key(SITE, "*", "*"),
                                                    monitor.on_token, history=True),
            session.declare_subscriber(keys.pose_key(SITE, "*"), monitor.on_pose)]
    pair = ("b1", "b2")
    runners = [ZenohRunner(OwnershipProbe(SITE, inst, ROBOTS, join_delay_s=0.0),
                           client_config(router)) for inst in pair]
    threads = [threading.Thread(target=r.run, daemon=True) for r in runners]
    want = {r: choose_owner(r, pair) for r in ROBOTS}
    try:
        for thread in threads:
            thread.start()
        assert wait_until(lambda: monitor.last_publishers() == want, 15.0, 0.02), (
            monitor.last_publishers(), want)
        time.sleep(0.5)
    finally:
        for runner in runners:
            runner.stop()
        for thread in threads:
            thread.join(10)
        for sub in subs:
            sub.undeclare()
        session.close()
    events = monitor.snapshot()
    problems = check_exclusive(events)
    trace = tmp_path / "bus.txt"
    trace.write_text("\n".join(" ".join(map(str, ev)) for ev in events))
    assert problems == [], (problems[:5], str(trace))
    conflicts = sum(r.node.table.counters["ownership.withdrawals"] for r in runners)
    print(f"simultaneous start: {conflicts} claims withdrawn, "
          f"{sum(r.node.table.counters['ownership.releases'] for r in runners)} released")


def test_a_frozen_backend_is_replaced_and_does_not_publish_when_it_thaws(
        router: str, tmp_path: Path) -> None:
    """SIGSTOP instead of SIGKILL: the router drops the frozen backend's session at its lease
    (1 s here, set in its zenoh config), the other backend takes its robot over; after SIGCONT
    the thawed backend publishes nothing while the other's token stands, and gets its robot
    back by a handover."""
    pair = ("b1", "b2")
    victim = choose_owner(ROBOTS[0], pair)
    (survivor,) = (i for i in pair if i != victim)
    want = {r: choose_owner(r, pair) for r in ROBOTS}
    config = tmp_path / "client.json5"
    config.write_text(json.dumps({
        "mode": "client", "connect": {"endpoints": [router]},
        "scouting": {"multicast": {"enabled": False}},
        "transport": {"link": {"tx": {"lease": 1000, "keep_alive": 4}}}}))
    monitor = BusMonitor()
    session = zenoh.open(client_config(router))
    subs = [session.liveliness().declare_subscriber(keys.owner_key(SITE, "*", "*"),
                                                    monitor.on_token, history=True),
            session.declare_subscriber(keys.pose_key(SITE, "*"), monitor.on_pose)]
    log = tmp_path / "victim.log"
    proc = subprocess.Popen(
        [sys.executable, "-m", "tests.system.ownership_probe", "--site", SITE, "--id", victim,
         "--robots", ",".join(ROBOTS), "--config", str(config)], cwd=REPO_ROOT,
        stdout=log.open("w"), stderr=subprocess.STDOUT)
    runner = ZenohRunner(OwnershipProbe(SITE, survivor, ROBOTS), client_config(router))
    thread = threading.Thread(target=runner.run, daemon=True)
    try:
        thread.start()
        assert wait_until(lambda: monitor.last_publishers() == want, 30.0, 0.05), (
            monitor.last_publishers(), want, log.read_text()[-3000:])
        stop_ns = time.time_ns()
        proc.send_signal(signal.SIGSTOP)
        assert wait_until(lambda: set(monitor.last_publishers().values()) == {survivor}, 5.0,
                          0.02), monitor.last_publishers()
        time.sleep(0.5)
        cont_ns = time.time_ns()
        proc.send_signal(signal.SIGCONT)
        assert wait_until(lambda: monitor.last_publishers() == want, 15.0, 0.05), (
            monitor.last_publishers(), want, log.read_text()[-3000:])
        time.sleep(0.5)
    finally:
        runner.stop()
        thread.join(10)
        if proc.poll() is None:
            proc.send_signal(signal.SIGCONT)
            stop_process(proc)
        for sub in subs:
            sub.undeclare()
        session.close()
    events = monitor.snapshot()
    trace = tmp_path / "bus.txt"
    trace.write_text("\n".join(" ".join(map(str, ev)) for ev in events))
    problems = check_exclusive(events)
    assert problems == [], (problems[:5], str(trace))
    orphans = [r for r in ROBOTS if want[r] == victim]
    taken_ms = max(min(ev[1] for ev in events if ev[0] == "pose" and ev[2] == r
                       and ev[1] > stop_ns and ev[3] == survivor) for r in orphans) - stop_ns
    back_ms = max(min(ev[1] for ev in events if ev[0] == "pose" and ev[2] == r
                      and ev[1] > cont_ns and ev[3] == victim) for r in orphans) - cont_ns
    # the survivor's own robots: a thawed backend that missed what happened meanwhile may
    # claim them, but only until its next liveliness get shows it the survivor
    gaps_ms = []
    for robot in (r for r in ROBOTS if want[r] == survivor):
        arrivals = [stop_ns] + [ev[1] for ev in events if ev[0] == "pose" and ev[2] == robot
                                and ev[1] > stop_ns]
        gaps_ms.append(max(b - a for a, b in itertools.pairwise(arrivals)) / 1e6)
    print(f"frozen backend {victim} ({orphans}): taken over {taken_ms / 1e6:.0f} ms after "
          f"SIGSTOP (lease 1 s); back to it {back_ms / 1e6:.0f} ms after SIGCONT; the "
          f"survivor's robots never stopped longer than {max(gaps_ms):.0f} ms")
    assert taken_ms <= FAILOVER_TARGET_S * NS_PER_S
    assert max(gaps_ms) <= FAILOVER_TARGET_S * 1e3


# ---------------------------------------------------------------- real backends

SIM_SITE_FILE = REPO_ROOT / "simulation" / "sites" / "paper_lab.yaml"
SIM_SITE = "paper_lab"
#: simulated seconds published, and when the robot's backend is killed
SIM_S = 12.0
KILL_S = 6.0


def test_a_killed_backend_s_robot_resumes_from_another_real_backend(tmp_path: Path) -> None:
    """Three real ``smartedge backend`` processes share the simulated site; the one that
    publishes the robot is SIGKILLed mid-run: fused poses resume from another backend within
    3 s, and never do two backends publish it at once. The estimates name no backend, but each
    backend numbers its fused poses (``seq``, one counter per robot track), and its poses
    arrive in order: one publisher gives rising numbers, a handover may step back once (the
    new owner's counter may lag), two publishers at once would step back and forth."""
    pytest.importorskip("gtsam")
    from simulation.runner import SimulationRun
    from simulation.scenario import load_scenario

    poses: list[tuple[int, int]] = []  # (arrival ns, seq) of the fused poses
    owners: list[tuple[int, str, bool]] = []  # (arrival ns, instance, present)
    details: dict[str, str] = {}

    def on_status(sample: Any) -> None:
        details[str(sample.key_expr).rsplit("/", 1)[1]] = decode(sample.payload.to_bytes()).detail

    with smartedge_router(tmp_path) as router:
        hub = zenoh.open(client_config(router))
        subs = [
            hub.declare_subscriber(keys.pose_key(SIM_SITE, "*"), lambda s: poses.append(
                (time.time_ns(), decode(s.payload.to_bytes()).seq))),
            hub.liveliness().declare_subscriber(
                keys.owner_key(SIM_SITE, "*", "*"), lambda s: owners.append(
                    (time.time_ns(), str(s.key_expr).rsplit("/", 1)[1],
                     s.kind == zenoh.SampleKind.PUT)), history=True),
            hub.declare_subscriber(keys.status_key(SIM_SITE, "backend", "*"), on_status),
        ]
        procs = {inst: subprocess.Popen(
            [sys.executable, "-m", "smartedge", "backend", "--site", str(SIM_SITE_FILE), "--id",
             inst, "--mode", "client", "--connect", router, "--no-multicast-scouting"],
            cwd=REPO_ROOT, stdout=(tmp_path / f"{inst}.log").open("w"),
            stderr=subprocess.STDOUT) for inst in INSTANCES}
        kill_ns, victim = 0, ""
        try:
            assert wait_until(lambda: len(details) == len(INSTANCES), 90, 0.1), details
            sc = load_scenario().with_overrides(start_stamp_ns=time.time_ns())
            run = SimulationRun(sc, "traj3", seed=3)
            qos = {"congestion_control": zenoh.CongestionControl.BLOCK,
                   "reliability": zenoh.Reliability.RELIABLE}
            pubs = {cam: hub.declare_publisher(keys.detections_key(SIM_SITE, cam), **qos)
                    for cam in run.camera_ids}
            odom = hub.declare_publisher(keys.odom_key(SIM_SITE, sc.robot_id), **qos)
            wall0 = time.monotonic()
            for tm in run.messages(until_s=SIM_S):
                t_s = (tm.arrival_ns - sc.start_stamp_ns) / NS_PER_S
                time.sleep(max(0.0, t_s - (time.monotonic() - wall0)))
                if t_s >= KILL_S and not victim:
                    held: set[str] = set()
                    for _, inst, present in list(owners):
                        (held.add if present else held.discard)(inst)
                    assert len(held) == 1, owners  # one robot, one owner
                    (victim,) = held
                    kill_ns = time.time_ns()
                    procs[victim].kill()
                if isinstance(tm.message, RobotDetections):
                    pubs[tm.message.camera_id].put(encode(tm.message))
                elif isinstance(tm.message, Odometry):
                    odom.put(encode(tm.message))
            time.sleep(1.0)
        finally:
            for proc in procs.values():
                if proc.poll() is None:
                    stop_process(proc)
            for sub in subs:
                sub.undeclare()
            hub.close()
    seqs = [seq for _, seq in poses]
    back = [(i, a, b) for i, (a, b) in enumerate(itertools.pairwise(seqs)) if b <= a]
    after = [t for t, _ in poses if t > kill_ns]
    assert len(back) <= 1, f"seq stepped back {len(back)} times (two publishers?): {back[:10]}"
    assert sum(1 for t, _ in poses if t <= kill_ns) > 50 and len(after) > 50
    resume_ms = (after[0] - kill_ns) / 1e6
    handover = [(round((t - kill_ns) / 1e6), inst, present) for t, inst, present in owners
                if t > kill_ns]
    print(f"real backends: {victim} killed; fused poses resumed after {resume_ms:.0f} ms; "
          f"owner tokens after the kill (ms, backend, present): {handover}")
    assert handover[0][1:] == (victim, False)  # the owner was killed
    assert any(present and inst != victim for _, inst, present in handover)  # and replaced
    assert resume_ms <= FAILOVER_TARGET_S * 1e3


def test_the_periodic_resync_goes_out_and_comes_back_without_blocking(router: str) -> None:
    """The liveliness gets that correct missed events every second leave at once
    (``start_sync``) and a later tick takes their answer (``poll_sync``): the worker no longer
    stands still for their round trip through the routers while frame-sets queue. The answer
    is the one the blocking start-up sync gives."""
    import zenoh

    from backend_service.ownership import OwnershipTable
    from backend_service.ownership_tokens import OwnershipTokens

    with zenoh.open(client_config(router)) as other, zenoh.open(client_config(router)) as mine:
        tokens_on_bus = [other.liveliness().declare_token(keys.alive_key("lab", "backend", "b9")),
                         other.liveliness().declare_token(keys.owner_key("lab", "r1", "b9"))]
        time.sleep(0.3)
        blocking = OwnershipTable("b1", ["r0", "r1"], started_ns=0)
        assert OwnershipTokens(mine, "lab", blocking).sync(time.time_ns) == 2
        table = OwnershipTable("b1", ["r0", "r1"], started_ns=0)
        tokens = OwnershipTokens(mine, "lab", table)
        t0 = time.perf_counter()
        tokens.start_sync()
        sent_s = time.perf_counter() - t0
        assert tokens.syncing and not table.is_synced
        answers: list[int | None] = []
        assert wait_until(lambda: answers.append(tokens.poll_sync(time.time_ns))
                          or answers[-1] is not None, 5.0, 0.001)
        assert answers[-1] == 2 and not tokens.syncing and table.is_synced
        assert sent_s < 0.05  # the gets' round trip was not waited for
        now = time.time_ns()
        assert table.members(now) == blocking.members(now) == ["b1", "b9"]
        assert table.summary(now) == blocking.summary(now)
        with pytest.raises(RuntimeError, match="without start_sync"):
            tokens.poll_sync(time.time_ns)
        for token in tokens_on_bus:
            token.undeclare()
