"""Areas of a site (issue 30: scaling out by splitting the cameras): the ``areas:`` section is
validated naming the file and key, a robot's area follows its position (polygon, hysteresis,
else the nearest camera), and ownership goes to the backends of the robot's area, with a
hand-over between areas that never has two publishers."""

from __future__ import annotations

import collections
import random
from typing import Any

import pytest

from backend_service.areas import AreaMap, backend_areas, parse_areas
from backend_service.ownership import OwnershipTable
from core.site import Site, parse_site
from protocol import keys
from protocol.errors import SiteConfigError

MS = 1_000_000
SITE_FILE = "facility.yaml"
#: cameras at x = 0, 4 (west) and 16, 20 (east); cam_mid at x = 10 sees both
CAMERA_X = {"cam_w0": 0.0, "cam_w1": 4.0, "cam_mid": 10.0, "cam_e0": 16.0, "cam_e1": 20.0}
WEST_POLY = [[-5, -5], [10, -5], [10, 5], [-5, 5]]
EAST_POLY = [[10, -5], [25, -5], [25, 5], [10, 5]]


def site_doc(areas: Any) -> dict[str, Any]:
    cams = [{"id": cid, "resolution": [848, 480],
             "intrinsics": {"fx": 428.0, "fy": 428.0, "cx": 424.0, "cy": 240.0},
             "T_world_cam": {"position_m": [x, -3.0, 2.5], "look_at_m": [x, 0.0, 0.2]}}
            for cid, x in CAMERA_X.items()]
    doc: dict[str, Any] = {
        "site": "facility", "cameras": cams,
        "robot_models": {"bot": {"footprint_radius_m": 0.2, "keypoints": [
            {"name": f"k{i}", "xyz_m": [0.1 * i, 0.05 * (i % 2), 0.3]} for i in range(4)]}},
        "robots": [{"id": "r1", "model": "bot"}, {"id": "r2", "model": "bot"}],
    }
    if areas is not None:
        doc["areas"] = areas
    return doc


def make_site(areas: Any) -> Site:
    return parse_site(site_doc(areas), SITE_FILE)


AREAS = {"west": {"cameras": ["cam_w0", "cam_w1", "cam_mid"], "polygon_m": WEST_POLY,
                  "backends": ["bw"]},
         "east": {"cameras": ["cam_mid", "cam_e0", "cam_e1"], "polygon_m": EAST_POLY}}


# ---------------------------------------------------------------------- the section


def test_areas_parse_with_a_border_camera_in_both() -> None:
    site = make_site(AREAS)
    areas = parse_areas(site)
    assert sorted(areas) == ["east", "west"]
    assert areas["west"].cameras == ("cam_w0", "cam_w1", "cam_mid")
    assert areas["west"].backends == ("bw",) and areas["east"].backends == ()
    amap = AreaMap(site)
    assert amap.camera_areas["cam_mid"] == ("west", "east")
    assert amap.cameras_of(["east"]) == ("cam_e0", "cam_e1", "cam_mid")
    assert amap.cameras_of(["west", "east"]) == tuple(sorted(CAMERA_X))
    assert not AreaMap(make_site(None)) and parse_areas(make_site(None)) == {}


@pytest.mark.parametrize("areas, key, words", [
    ({"west": {"cameras": ["cam_w0", "cam_nope"]}}, "areas.west.cameras[1]", "no camera"),
    ({"west": {"cameras": []}}, "areas.west.cameras", "non-empty"),
    ({"west": {}}, "areas.west.cameras", "missing"),
    ({"west": {"cameras": ["cam_w0", "cam_w0"]}}, "areas.west.cameras[1]", "twice"),
    ({"west": {"cameras": ["cam_w0"], "polygon_m": [[0, 0], [1, 1]]}}, "areas.west.polygon_m",
     "at least 3"),
    ({"west": {"cameras": ["cam_w0"], "polygon_m": [[0, 0], [1, 1], [2, 2]]}},
     "areas.west.polygon_m", "no area"),
    ({"west": {"cameras": ["cam_w0"], "polygon_m": [0, 1, 2]}}, "areas.west.polygon_m",
     "[x, y]"),
    ({"west": {"cameras": ["cam_w0"], "floor": 1}}, "areas.west", "floor"),
    ({"bad name": {"cameras": ["cam_w0"]}}, "areas.bad name", "invalid id"),
    ({"west": ["cam_w0"]}, "areas.west", "map"),
])
def test_a_wrong_area_is_refused_naming_the_file_and_key(areas, key, words) -> None:
    site = make_site(areas)
    with pytest.raises(SiteConfigError) as err:
        parse_areas(site)
    text = str(err.value)
    assert SITE_FILE in text and key in text and words in text, text


def test_a_site_file_without_the_section_key_refuses_nothing_and_a_typo_is_refused() -> None:
    with pytest.raises(SiteConfigError, match="area"):
        parse_site({**site_doc(None), "area": {"west": {"cameras": ["cam_w0"]}}}, SITE_FILE)


def test_the_areas_of_a_backend_come_from_area_or_from_the_site_list() -> None:
    site = make_site(AREAS)
    assert backend_areas(site, ["east"], "bw") == ("east",)
    assert backend_areas(site, [], "bw") == ("west",)  # the site lists bw under west
    assert backend_areas(site, [], "other") == ()  # every camera
    with pytest.raises(SiteConfigError) as err:
        backend_areas(site, ["north"], "b0")
    assert SITE_FILE in str(err.value) and "areas.north" in str(err.value)
    assert "east, west" in str(err.value)


# ---------------------------------------------------------------------- area of a position


def test_a_robot_is_in_the_area_of_its_polygon_and_stays_near_a_border() -> None:
    amap = AreaMap(make_site(AREAS))
    assert amap.area_of(2.0, 0.0) == "west"
    assert amap.area_of(12.0, 0.0) == "east"
    # 0.3 m past the border: still in the area it came from (hysteresis), then it changes
    assert amap.area_of(10.3, 0.0, "west") == "west"
    assert amap.area_of(9.7, 0.0, "east") == "east"
    assert amap.area_of(10.0 + amap.hysteresis_m + 0.2, 0.0, "west") == "east"
    # outside every polygon: the nearest camera's area, and the nearest polygon among its areas
    assert amap.area_of(-8.0, 0.0) == "west" and amap.area_of(30.0, 0.0) == "east"


def test_without_polygons_a_robot_goes_to_the_area_of_the_nearest_camera() -> None:
    areas = {"west": {"cameras": ["cam_w0", "cam_w1"]},
             "east": {"cameras": ["cam_e0", "cam_e1"]}}
    amap = AreaMap(make_site(areas))
    assert amap.area_of(3.0, 0.5) == "west" and amap.area_of(17.0, 0.5) == "east"
    assert amap.area_of(10.1, 0.0) == "east"  # nearer cam_e0 (16) than cam_w1 (4)? no: 6.1 vs 5.9
    assert amap.area_of(9.9, 0.0) == "west"
    # hysteresis: a robot from the west stays west until the east camera is clearly nearer
    assert amap.area_of(10.1, 0.0, "west") == "west"
    assert amap.area_of(10.6, 0.0, "west") == "east"


# ---------------------------------------------------------------------- ownership by area


class AreaBus:
    """Backends' ownership tables on a bus that delivers every token event after 1-8 ms (per
    receiver, in order), and the robots' poses to every table after 0-30 ms (so their views of
    a robot's area differ for a while); at most one backend may publish a robot at any ms."""

    def __init__(self, site: Site, served: dict[str, tuple[str, ...]], seed: int = 0) -> None:
        self.rng = random.Random(seed)
        self.robots = sorted(site.robots)
        amap = AreaMap(site)
        self.t_ms = 0
        self.tables = {inst: OwnershipTable(inst, self.robots, started_ns=0, confirm_s=0.05,
                                            join_delay_s=0.0, stall_s=1.0, areas=amap,
                                            own_areas=areas)
                       for inst, areas in served.items()}
        for table in self.tables.values():
            table.resync(list(served), [], 0,
                         [(a, i) for i, areas in served.items() for a in areas])
        self.queue: list[tuple[int, str, Any]] = []
        self.last: dict[str, int] = collections.defaultdict(int)
        self.publisher: dict[str, list[tuple[int, str | None]]] = {r: [] for r in self.robots}

    def _send(self, to: str, event: Any, delay: tuple[int, int]) -> None:
        at = max(self.t_ms + self.rng.randint(*delay), self.last[to])
        self.last[to] = at
        self.queue.append((at, to, event))

    def move(self, robot: str, x: float, y: float) -> None:
        for inst in self.tables:
            self.queue.append((self.t_ms + self.rng.randint(0, 30), inst,
                               ("pose", robot, x, y, self.t_ms * MS)))

    def step(self) -> None:
        self.t_ms += 1
        now = self.t_ms * MS
        due = sorted((e for e in self.queue if e[0] <= self.t_ms), key=lambda e: e[0])
        self.queue = [e for e in self.queue if e[0] > self.t_ms]
        for _, to, event in due:
            table = self.tables[to]
            if event[0] == "pose":
                table.on_robot_position(event[1], event[2], event[3], event[4])
            else:
                _, robot, owner, present = event
                assert table.on_liveliness("facility", keys.owner_key("facility", robot, owner),
                                           present, now)
        if self.t_ms % 10 == 0:
            for inst, table in self.tables.items():
                decision = table.decide(now)
                for robot in decision.release:
                    for other in self.tables:
                        if other != inst:
                            self._send(other, ("owner", robot, inst, False), (1, 8))
                for robot in decision.claim:
                    for other in self.tables:
                        if other != inst:
                            self._send(other, ("owner", robot, inst, True), (1, 8))
        for robot in self.robots:
            pubs = [i for i, t in self.tables.items() if t.may_publish(robot, now)]
            assert len(pubs) <= 1, f"{robot} published by {pubs} at {self.t_ms} ms"
            who = pubs[0] if pubs else None
            log = self.publisher[robot]
            if not log or log[-1][1] != who:
                log.append((self.t_ms, who))

    def run(self, ms: int) -> None:
        for _ in range(ms):
            self.step()

    def now_publishing(self, robot: str) -> str | None:
        return self.publisher[robot][-1][1] if self.publisher[robot] else None


@pytest.mark.parametrize("seed", range(4))
def test_a_robot_is_owned_by_its_areas_backend_and_handed_over_when_it_crosses(seed) -> None:
    site = make_site(AREAS)
    bus = AreaBus(site, {"bw": ("west",), "be": ("east",)}, seed)
    bus.move("r1", 2.0, 0.0)
    bus.move("r2", 18.0, 0.0)
    bus.run(400)
    assert bus.now_publishing("r1") == "bw" and bus.now_publishing("r2") == "be"
    assert bus.tables["bw"].owned() == ["r1"] and bus.tables["be"].owned() == ["r2"]
    releases = bus.tables["bw"].counters["ownership.releases"]
    # r1 drives east across the border, 0.1 m per 20 ms (5 m/s, a quick hand-over test)
    x, crossed_ms = 2.0, None
    while x < 14.0:
        x += 0.1
        bus.move("r1", x, 0.0)
        bus.run(20)
        if crossed_ms is None and x > 10.0 + AreaMap(site).hysteresis_m:
            crossed_ms = bus.t_ms
    bus.run(400)
    assert bus.now_publishing("r1") == "be" and bus.tables["be"].owned() == ["r1", "r2"]
    assert bus.tables["bw"].owned() == []
    assert bus.tables["bw"].counters["ownership.releases"] == releases + 1
    assert bus.tables["be"].counters["ownership.area_changes"] == 1
    # the gap without a publisher: the claim after the old token vanished plus the
    # confirmation, a few frame-sets at 15 Hz
    gaps = [b[0] - a[0] for a, b in zip(bus.publisher["r1"], bus.publisher["r1"][1:], strict=False)
            if a[1] is None and a[0] > 400]
    assert gaps and max(gaps) < 200, bus.publisher["r1"]
    assert crossed_ms is not None


def test_a_robot_whose_area_has_no_live_backend_goes_to_another_and_comes_back() -> None:
    site = make_site(AREAS)
    bus = AreaBus(site, {"bw": ("west",)})
    bus.move("r2", 18.0, 0.0)  # east: nobody serves it
    bus.run(300)
    assert bus.now_publishing("r2") == "bw"
    table = bus.tables["bw"]
    assert table.candidates("r2", bus.t_ms * MS) == ["bw"]


def test_a_backend_without_area_serves_every_area_and_unknown_area_tokens_are_counted() -> None:
    site = make_site(AREAS)
    table = OwnershipTable("be", ["r1", "r2"], started_ns=0, join_delay_s=0.0,
                           areas=AreaMap(site), own_areas=("east",))
    table.resync(["be", "ball", "bw"], [], 0, [("east", "be"), ("west", "bw"),
                                                ("north", "bx")])
    assert table.counters["ownership.unknown_area_tokens"] == 1
    table.on_robot_position("r1", 2.0, 0.0, 1)
    assert table.candidates("r1", 1) == ["ball", "bw"]
    table.on_robot_position("r1", 14.0, 0.0, 2)
    assert table.candidates("r1", 2) == ["ball", "be"]
    table.on_robot_position("r1", 2.0, 0.0, 1)  # older than the newest: ignored
    assert table.robot_area("r1") == "east"
    # bw's token goes: bw serves every area (a backend without area tokens)
    table.on_liveliness("facility", keys.area_key("facility", "west", "bw"), False, 3)
    assert table.candidates("r1", 3) == ["ball", "be", "bw"]
    with pytest.raises(ValueError, match="north"):
        OwnershipTable("b", ["r1"], started_ns=0, areas=AreaMap(site), own_areas=("north",))


def test_a_robot_of_unknown_area_waits_for_its_first_pose_then_goes_to_anybody() -> None:
    site = make_site(AREAS)
    table = OwnershipTable("be", ["r1"], started_ns=0, join_delay_s=0.0, confirm_s=0.0,
                           areas=AreaMap(site), own_areas=("east",))
    table.resync(["be"], [], 0)
    assert table.decide(100 * MS).claim == ()  # no pose of r1 yet: nobody claims it
    assert table.candidates("r1", 100 * MS) == []
    later = round((table.area_grace_ns + 1) * 1.0)
    assert table.decide(later).claim == ("r1",)  # still unknown after the grace: by score
    table.on_robot_position("r1", 2.0, 0.0, later)  # west: nobody serves it but be
    assert table.owner_of("r1", later) == "be"


def test_on_zenoh_the_area_tokens_give_a_robot_to_its_areas_backend_and_hand_it_over(
        zenoh_pair) -> None:
    """Two backends' ownership on two real sessions: each declares its area token, learns the
    other's, gives r1 to the west backend while it is in the west and hands it to the east
    one when it crosses; at no check do both publish it."""
    import threading
    import time

    from backend_service.ownership_tokens import BackendOwnership
    from tests.conftest import wait_until

    zenoh = pytest.importorskip("zenoh")
    listener, connector, _ = zenoh_pair
    amap = AreaMap(make_site(AREAS))
    events: list[tuple[BackendOwnership, str, bool]] = []
    lock = threading.Lock()
    handles, backends = [], {}
    for inst, area, session in (("bw", "west", listener), ("be", "east", connector)):
        own = BackendOwnership("facility", inst, ["r1", "r2"], started_ns=time.time_ns(),
                               confirm_s=0.05, join_delay_s=0.0, areas=amap,
                               own_areas=(area,))
        for sub in own.subscriptions():
            def on_token(sample, _own=own) -> None:
                with lock:
                    events.append((_own, str(sample.key_expr),
                                   sample.kind == zenoh.SampleKind.PUT))
            handles.append(session.liveliness().declare_subscriber(sub.key_expr, on_token,
                                                                   history=True))
        own.attach(session, time.time_ns)
        handles.append(session.liveliness().declare_token(
            keys.alive_key("facility", "backend", inst)))
        backends[inst] = own

    publishers: list[tuple[str | None, str | None]] = []

    def run_for(seconds: float, x_m: float) -> None:
        end = time.monotonic() + seconds
        while time.monotonic() < end:
            now = time.time_ns()
            with lock:
                pending = events[:]
                events.clear()
            for own, key, present in pending:
                own.alive(key, present, now)
            for own in backends.values():
                own.observe("r1", x_m, 0.0, now)
                own.observe("r2", 18.0, 0.0, now)
                own.tick(now)
            now = time.time_ns()
            pubs = {r: [i for i, o in backends.items() if o.may_publish(r, now)]
                    for r in ("r1", "r2")}
            assert all(len(p) <= 1 for p in pubs.values()), pubs
            publishers.append((pubs["r1"][0] if pubs["r1"] else None,
                               pubs["r2"][0] if pubs["r2"] else None))
            time.sleep(0.01)

    try:
        assert wait_until(lambda: any(r.ok is not None for r in listener.liveliness().get(
            keys.area_key("facility", "east", "be"), timeout=1.0)), 5)
        run_for(2.0, 2.0)
        assert publishers[-1] == ("bw", "be"), publishers[-5:]
        assert backends["bw"].table._member_areas == {"be": {"east"}}
        run_for(2.0, 14.0)  # r1 crossed into the east
        assert publishers[-1] == ("be", "be"), publishers[-5:]
        assert backends["bw"].table.owned() == [] and backends["be"].table.owned() == ["r1",
                                                                                       "r2"]
    finally:
        for h in handles:
            h.undeclare()
        for own in backends.values():
            own.close()
