"""``smartedge bench fleet``: a simulated facility on loopback (the scale benchmark).

R ``smartedge router`` processes connected in a chain (router k connects to router k-1), B
``smartedge backend`` processes (backend j a client of router j mod R) sharing the site's robots
by their ownership tokens, and this process as the facility's cameras and robots: N robots, each
driving a slow circle in its own cell of a row of cells (12 m apart), M cameras spread over the
cells on rings of 4 m around the cell centres. Every camera reports every robot it sees, unnamed
and in one message per image, at F Hz (stamped with the capture time; the backends match the
detections to robots); each robot's bridge sends its odometry (``--odom-rate``) and its own
localization (5 Hz, so the backends can predict it before the cameras localize it). The cameras
of cell c publish through router c mod R (the router of their area), the robots through router 0.
Every frame's payloads are projected and encoded before the run (the cameras do that on their own
boards), so only sending them shares the cores with the services.

Two ways to split the facility over the backends (``--split``, one set of rows each):

- ``none``: every backend receives every camera's detections and the backends share the robots by
  the rendezvous hash (each still decodes, associates and synchronizes every camera);
- ``area``: the site has one area per router (``a<k>``: the cameras of the cells c with
  c mod R = k, backend_service/areas.py) and backend j serves the areas k with k mod B = j
  (``smartedge backend --area``): it subscribes to those cameras only and owns the robots in
  them (backend j connects to router j mod R, so with B = R each backend is on its area's
  router).

Measured per backend count (one row each, everything restarted):

- detection-to-pose latency: the frame-set's stamp to the arrival of the robot's camera pose on
  the bus (a subscriber here, on the last router): both Zenoh hops and the router chain, the
  synchronizer, association and the solve; p50/p99 over all robots;
- frame-sets without a pose (per robot, a stamp at which a camera saw it and no pose came), next
  to the counters the backends report for what they dropped (``shed``, ``stale_dropped``, sync
  overflow, ``no_estimate``): a frame-set missing without a counter is dropped *silently*;
- two publishers: a (robot, stamp) pose received more than once;
- CPU per process (seconds of CPU per second over the measured span, from /proc), and each
  backend's by thread: its worker, Zenoh's runtime, and the rest (callback threads, a BLAS
  library's: busy there is work nobody scheduled);
- the worst frames (when in the span, how late their slowest pose): a tail that comes back at
  the same moments in every run is triggered by the traffic, not by the host;
- with ``--latencies CSV``, every measured pose's latency, for plots and for comparing runs.
"""

from __future__ import annotations

import argparse
import dataclasses
import gc
import json
import logging
import math
import os
import platform
import tempfile
import time
from collections.abc import Sequence
from pathlib import Path
from typing import Any, Final

import numpy as np
import yaml

from core.geometry import rotation_z
from core.site import Site, load_site
from lab.launcher import (
    LaunchError,
    ServiceProcess,
    free_port,
    start_service,
    stop_services,
)
from protocol import decode, encode, keys
from protocol.messages import Detection, Odometry, PoseEstimate, RobotDetections, ServiceStatus

REPO_ROOT: Final = Path(__file__).resolve().parents[2]
ROUTER_CONFIG: Final = REPO_ROOT / "deploy" / "zenoh" / "router.json5"
CELL_SPACING_M: Final = 12.0
RING_RADIUS_M: Final = 4.0
CAMERA_HEIGHT_M: Final = 2.5
#: a detector's range: robots farther from a camera than this are not reported (they are a
#: few pixels tall in an 848x480 image)
MAX_RANGE_M: Final = 8.0
ROBOT_CIRCLE_M: Final = 0.5
ROBOT_SPEED_MPS: Final = 0.2
LOCALIZATION_RATE_HZ: Final = 5.0
#: the backends' counters that account for a frame-set without a pose (detections shed or
#: left unassigned, frame-sets overflowing the synchronizer, solves without an estimate, poses
#: too old to publish)
DROP_COUNTERS: Final = ("shed", "stale_dropped.camera_pose", "sync.overflow", "sync.late",
                        "sync.rate_limited", "no_estimate", "ownership.withheld",
                        "association.detections_ambiguous",
                        "association.detections_no_prediction",
                        "association.detections_unassigned")
SITE_NAME: Final = "fleet"
SPLITS: Final = ("none", "area")


@dataclasses.dataclass(frozen=True)
class FleetLayout:
    """Where the robots drive and the cameras look: robot ``i`` circles the centre of cell
    ``i``; camera ``k`` belongs to cell ``k mod N`` (``cell_of``)."""

    robot_ids: tuple[str, ...]
    cell_of: dict[str, int]  # camera id -> cell

    def centre(self, cell: int) -> tuple[float, float]:
        return (cell * CELL_SPACING_M, 0.0)

    def robot_pose(self, index: int, t_s: float) -> np.ndarray:
        """(x, y, theta) of robot ``index`` at ``t_s``: a circle in its cell (phase by index)."""
        cx, cy = self.centre(index)
        w = ROBOT_SPEED_MPS / ROBOT_CIRCLE_M
        a = w * t_s + 0.7 * index
        return np.array([cx + ROBOT_CIRCLE_M * math.cos(a), cy + ROBOT_CIRCLE_M * math.sin(a),
                         math.remainder(a + math.pi / 2, 2 * math.pi)])


def area_name(k: int) -> str:
    return f"a{k}"


def backend_areas_of(backend: int, n_backends: int, n_areas: int) -> list[str]:
    """The areas backend ``backend`` of ``n_backends`` serves in the ``area`` split: those
    ``k`` with ``k mod n_backends == backend`` (all of them for one backend; none when there are
    more backends than areas and this one is beyond them: it then serves every camera)."""
    return [area_name(k) for k in range(n_areas) if k % n_backends == backend]


def write_fleet_site(path: Path, n_robots: int, n_cameras: int, n_areas: int = 0
                     ) -> tuple[Site, FleetLayout]:
    """A site file of ``n_robots`` HSR-like robots (each in its own ROS namespace) and
    ``n_cameras`` cameras, spread over one cell per robot; with ``n_areas``, an ``areas:``
    section of that many areas, area ``a<k>`` the cameras of the cells c with c mod n_areas =
    k (the cells of router k; no polygon: a robot is in the area of its nearest camera)."""
    from simulation.scenario import load_scenario

    if n_robots < 1 or n_cameras < 1:
        raise ValueError(f"fleet bench: need at least one robot and one camera, got "
                         f"{n_robots} robots, {n_cameras} cameras")
    model = load_scenario().site.robot_model()
    robot_ids = tuple(f"robot{i:02d}" for i in range(n_robots))
    cameras, cell_of = [], {}
    per_cell = [sum(1 for k in range(n_cameras) if k % n_robots == c) for c in range(n_robots)]
    for k in range(n_cameras):
        cell, slot = k % n_robots, k // n_robots
        a = 2 * math.pi * slot / per_cell[cell] + 0.4 * cell
        cx, cy = cell * CELL_SPACING_M, 0.0
        cam_id = f"cam{k:03d}"
        cell_of[cam_id] = cell
        cameras.append({
            "id": cam_id, "resolution": [848, 480],
            "intrinsics": {"fx": 428.0, "fy": 428.0, "cx": 424.0, "cy": 240.0},
            "distortion": [-0.055, 0.065, 0.0, 0.0, -0.02],
            "T_world_cam": {"position_m": [cx + RING_RADIUS_M * math.cos(a),
                                           cy + RING_RADIUS_M * math.sin(a), CAMERA_HEIGHT_M],
                            "look_at_m": [cx, cy, 0.2]},
        })
    doc = {
        "site": SITE_NAME, "cameras": cameras,
        "robot_models": {"hsr": {
            "footprint_radius_m": model.footprint_radius_m, "height_m": model.height_m,
            "keypoints": [{"name": n, "xyz_m": [float(v) for v in p]}
                          for n, p in zip(model.keypoint_names, model.keypoints_base_m,
                                          strict=True)]}},
        "robots": [{"id": rid, "model": "hsr", "ros": {"namespace": rid}} for rid in robot_ids],
        "thresholds": {"sync_window_ms": 10.0, "sync_max_wait_ms": 50.0},
    }
    if n_areas:
        areas = {area_name(k): {"cameras": [c for c, cell in cell_of.items()
                                            if cell % n_areas == k]}
                 for k in range(n_areas)}
        doc["areas"] = {k: v for k, v in areas.items() if v["cameras"]}
    path.write_text(yaml.safe_dump(doc))
    return load_site(path), FleetLayout(robot_ids, cell_of)


@dataclasses.dataclass
class PreparedRun:
    """Every message of a run, encoded, in send order: ``frames[k]`` = (stamp ns, [(key,
    payload, cell)]) with cell -1 for the robots' own messages (sent through router 0);
    ``seen[(robot, stamp)]``: the frame-sets in which at least one camera saw the robot."""

    start_ns: int
    frames: list[tuple[int, list[tuple[str, bytes, int]]]]
    seen: set[tuple[str, int]]


def camera_detections(site: Site, layout: FleetLayout, poses: np.ndarray, stamp_ns: int,
                      seq: int, rng: np.random.Generator
                      ) -> tuple[list[tuple[str, bytes, int]], set[str]]:
    """Each camera's unnamed detections of every robot wholly in its image and within
    :data:`MAX_RANGE_M` in front of it (1 px keypoint noise, shuffled), encoded; and the
    robots some camera saw."""
    model = site.robot_model(layout.robot_ids[0])
    pts = [model.keypoints_base_m @ rotation_z(p[2]).T + [p[0], p[1], 0.0] for p in poses]
    out, seen = [], set()
    for cam in site.cameras.values():
        dets = []
        for rid, p in zip(layout.robot_ids, pts, strict=True):
            uv, depth = cam.project(p)
            if not (np.all(depth > 0.3) and np.all(depth < MAX_RANGE_M)
                    and np.all(cam.in_image(uv, 2.0))):
                continue
            uv = uv + rng.normal(0.0, 1.0, uv.shape)
            lo, hi = uv.min(axis=0) - 5, uv.max(axis=0) + 5
            dets.append(Detection(np.array([*lo, *hi]), 0.95, uv, np.full(len(uv), 0.9)))
            seen.add(rid)
        rng.shuffle(dets)
        msg = RobotDetections(cam.camera_id, stamp_ns, seq, cam.width, cam.height, "bench",
                              tuple(dets))
        out.append((keys.detections_key(site.name, cam.camera_id), encode(msg),
                    layout.cell_of[cam.camera_id]))
    return out, seen


def prepare_run(site: Site, layout: FleetLayout, rate_hz: float, odom_rate_hz: float,
                seconds: float, rng: np.random.Generator) -> PreparedRun:
    """Every camera frame, odometry and localization message of ``seconds``, encoded now; the
    first stamp lies far enough ahead (the preparation time of two frames, extrapolated and
    doubled, plus a second) for the preparation to finish."""
    n_frames = int(seconds * rate_hz)
    t0 = time.perf_counter()
    for k in range(2):
        camera_detections(site, layout, np.stack([layout.robot_pose(i, 0.0) for i in
                                                  range(len(layout.robot_ids))]), 0, k, rng)
    per_frame_s = (time.perf_counter() - t0) / 2
    start_ns = time.time_ns() + round((2.0 * per_frame_s * n_frames + 1.0) * 1e9)
    events: list[tuple[int, int, list[tuple[str, bytes, int]]]] = []  # (stamp, order, msgs)
    seen: set[tuple[str, int]] = set()
    w = ROBOT_SPEED_MPS / ROBOT_CIRCLE_M
    n = len(layout.robot_ids)
    for k in range(n_frames):
        stamp = start_ns + round(k * 1e9 / rate_hz)
        t_s = k / rate_hz
        poses = np.stack([layout.robot_pose(i, t_s) for i in range(n)])
        msgs, robots = camera_detections(site, layout, poses, stamp, k, rng)
        seen.update((rid, stamp) for rid in robots)
        events.append((stamp, 0, msgs))
    for k in range(int(seconds * odom_rate_hz)):
        stamp = start_ns + round(k * 1e9 / odom_rate_hz)
        t_s = k / odom_rate_hz
        msgs = []
        for i, rid in enumerate(layout.robot_ids):
            x, y, th = layout.robot_pose(i, t_s)
            odom = Odometry(rid, stamp, k, float(x), float(y), float(th), ROBOT_SPEED_MPS, 0.0,
                            w, np.diag([1e-4, 1e-4, 1e-4]))
            msgs.append((keys.odom_key(site.name, rid), encode(odom), -1))
        events.append((stamp, 1, msgs))
    for k in range(int(seconds * LOCALIZATION_RATE_HZ)):
        stamp = start_ns + round(k * 1e9 / LOCALIZATION_RATE_HZ)
        t_s = k / LOCALIZATION_RATE_HZ
        msgs = []
        for i, rid in enumerate(layout.robot_ids):
            x, y, th = layout.robot_pose(i, t_s)
            loc = PoseEstimate(rid, stamp, k, float(x), float(y), float(th),
                               np.diag([0.05, 0.05, 0.02]) ** 2, "robot")
            msgs.append((keys.localization_key(site.name, rid), encode(loc), -1))
        events.append((stamp, 2, msgs))
    events.sort(key=lambda e: (e[0], e[1]))
    return PreparedRun(start_ns, [(s, m) for s, _, m in events], seen)


def client_config(endpoint: str) -> Any:
    """A Zenoh client session's config on one router endpoint, scouting off."""
    import zenoh

    doc = {"mode": "client", "connect": {"endpoints": [endpoint]},
           "scouting": {"multicast": {"enabled": False}}}
    return zenoh.Config.from_json5(json.dumps(doc))


def _stat_cpu_s(stat: str) -> float:
    """CPU seconds (user + system) in the text of a /proc ``stat`` file (a process's or a
    thread's)."""
    fields = stat.rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def _cpu_s(pid: int) -> float:
    """CPU seconds (user + system) of a process so far; NaN when /proc cannot tell."""
    try:
        return _stat_cpu_s(Path(f"/proc/{pid}/stat").read_text())
    except (OSError, ValueError, IndexError):
        return math.nan


#: thread names (``/proc/<pid>/task/<tid>/comm``) of Zenoh's runtime in a Python process
ZENOH_THREAD_PREFIXES: Final = ("app-", "net-", "tx-", "rx-", "acc-", "Watchdog")
THREAD_CLASSES: Final = ("worker", "zenoh", "other")


def _thread_cpu_s(pid: int) -> dict[str, float]:
    """CPU seconds so far of a service's threads by class: ``worker`` (the main thread, where
    the runner's loop runs), ``zenoh`` (Zenoh's runtime threads), ``other`` (the rest: the
    subscriptions' callback threads, a BLAS library's, a compiler's); empty when /proc cannot
    tell. A busy ``other`` is work nobody scheduled: numpy's BLAS thread spinning after a
    split call was the fleet's latency tail (docs/benchmarks.md, "The BLAS thread")."""
    out = dict.fromkeys(THREAD_CLASSES, 0.0)
    try:
        tasks = os.listdir(f"/proc/{pid}/task")
    except OSError:
        return {}
    for tid in tasks:
        try:
            stat = Path(f"/proc/{pid}/task/{tid}/stat").read_text()
        except OSError:
            continue  # the thread ended
        name = stat[stat.find("(") + 1:stat.rfind(")")]
        cls = ("worker" if int(tid) == pid else
               "zenoh" if name.startswith(ZENOH_THREAD_PREFIXES) else "other")
        out[cls] += _stat_cpu_s(stat)
    return out


@dataclasses.dataclass
class RowResult:
    backends: int
    split: str
    p50_ms: float
    p99_ms: float
    max_ms: float
    poses: int
    frame_sets: int
    missing: int
    accounted: int  # counters of the backends that account for missing frame-sets
    duplicates: int
    late_publish: int
    cpu: dict[str, float]  # process name -> CPU s per s
    counters: dict[str, int]
    stage_ms: dict[str, float]  # backend's own stage p99 (ms), worst backend
    owners: dict[str, str]  # backend -> the robots its status says it owns
    statuses_in_span: dict[str, int]  # backend -> statuses received over the measured span
    unreadable_statuses: int
    missing_at: list[tuple[str, float]]  # the first missing frame-sets: (robot, s into the span)
    received: dict[str, int]  # backend -> camera messages its synchronizer received (all run)
    areas: dict[str, str]  # backend -> the areas it served ("all": every camera)
    load1: float = math.nan  # the machine's 1-minute load average at the end of the span
    #: how long after its stamp a measured camera frame was all sent (ms): p99 and max. The
    #: latency includes it; a figure near the latency's tail says the publisher was behind
    send_lag_ms: tuple[float, float] = (math.nan, math.nan)
    #: backend -> CPU s per s of its threads by class (:func:`_thread_cpu_s`)
    thread_cpu: dict[str, dict[str, float]] = dataclasses.field(default_factory=dict)
    #: every measured pose: (robot, its frame-set's stamp in s into the span, latency ms)
    latencies: list[tuple[str, float, float]] = dataclasses.field(default_factory=list)

    @property
    def silent(self) -> int:
        return max(0, self.missing - self.accounted)


@dataclasses.dataclass(frozen=True)
class FleetRow:
    """One row of the benchmark: the facility and its traffic. ``rate_hz``: each camera's
    frames per second; ``odom_rate_hz``: each robot's odometry; ``warmup_s`` unmeasured, then
    ``seconds`` measured; ``split``: ``none`` (every backend receives every camera) or
    ``area`` (one area per router, see the module doc)."""

    backends: int
    routers: int
    robots: int
    cameras: int
    rate_hz: float
    odom_rate_hz: float
    seconds: float
    warmup_s: float
    split: str = "none"


def run_row(row: FleetRow, workdir: Path, progress: bool = True) -> RowResult:
    """One row: fresh routers and backends, ``row.warmup_s`` + ``row.seconds`` of traffic;
    only the frame-sets stamped after the warm-up are measured."""
    import zenoh

    n_backends, n_routers, n_robots, n_cameras = row.backends, row.routers, row.robots, row.cameras
    rate_hz, odom_rate_hz, seconds, warmup_s = (row.rate_hz, row.odom_rate_hz, row.seconds,
                                                row.warmup_s)
    split = row.split

    if split not in SPLITS:
        raise ValueError(f"split must be one of {SPLITS}, got {split!r}")
    site_path = workdir / "fleet_site.yaml"
    n_areas = n_routers if split == "area" else 0
    site, layout = write_fleet_site(site_path, n_robots, n_cameras, n_areas)
    served = {f"b{b}": (backend_areas_of(b, n_backends, len(site.section("areas")))
                        if n_areas else []) for b in range(n_backends)}
    procs: dict[str, ServiceProcess] = {}
    endpoints: list[str] = []
    try:
        for r in range(n_routers):
            port = free_port()
            endpoint = f"tcp/127.0.0.1:{port}"
            procs[f"router{r}"] = start_service(
                ["router", "--config", str(ROUTER_CONFIG), "--listen", endpoint,
                 *(("--connect", endpoints[-1]) if endpoints else ())],
                workdir / f"router{r}.log", name=f"router{r}", cwd=REPO_ROOT)
            procs[f"router{r}"].wait_listening(port, timeout_s=30.0)
            endpoints.append(endpoint)
        for b in range(n_backends):
            procs[f"backend{b}"] = start_service(
                ["backend", "--site", str(site_path), "--id", f"b{b}", "--mode", "client",
                 "--connect", endpoints[b % n_routers], "--no-multicast-scouting",
                 *(a for area in served[f"b{b}"] for a in ("--area", area))],
                workdir / f"backend{b}.log", name=f"backend{b}", log_level="WARNING",
                cwd=REPO_ROOT)
        poses: list[tuple[int, str, bytes]] = []  # (arrival ns, robot, payload)
        statuses: dict[str, ServiceStatus] = {}
        history: list[ServiceStatus] = []  # every status, in arrival order
        bad_status = [0]

        def on_status(sample: Any) -> None:
            try:
                st = decode(sample.payload.to_bytes())
            except Exception:  # counted and shown: a status the monitor cannot read
                bad_status[0] += 1
                return
            if isinstance(st, ServiceStatus):
                statuses[st.instance_id] = st
                history.append(st)

        sessions = [zenoh.open(client_config(e)) for e in endpoints]
        try:
            monitor = sessions[-1]
            monitor.declare_subscriber(
                keys.camera_pose_key(site.name, "*"),
                lambda s: poses.append((time.time_ns(), str(s.key_expr).split("/")[3],
                                        s.payload.to_bytes())))
            monitor.declare_subscriber(keys.status_key(site.name, "backend", "*"), on_status)
            deadline = time.monotonic() + 90
            while len(statuses) < n_backends and time.monotonic() < deadline:
                for name, p in procs.items():
                    if not p.running():
                        raise LaunchError(f"{name} exited with {p.returncode}; see "
                                          f"{p.log_path}:\n{p.log_tail()}")
                time.sleep(0.1)
            if len(statuses) < n_backends:
                raise RuntimeError(f"only {sorted(statuses)} of {n_backends} backends started; "
                                   f"see {workdir}")
            qos = {"congestion_control": zenoh.CongestionControl.BLOCK}
            pubs: dict[str, Any] = {}
            if progress:
                print(f"  {n_backends} backend(s) up; encoding "
                      f"{int((seconds + warmup_s) * rate_hz)} frames of {n_cameras} cameras",
                      flush=True)
            prepared = prepare_run(site, layout, rate_hz, odom_rate_hz, seconds + warmup_s,
                                   np.random.default_rng(0))
            measured_from = prepared.start_ns + round(warmup_s * 1e9)
            late, period_ns = 0, round(1e9 / rate_hz)
            cpu0: dict[str, float] = {}
            lag_ns: list[int] = []  # how late each measured camera frame went out
            # the encoded frames are kept to the end: out of the collector's view, and no
            # collection while sending (a full one of this process took tens of ms: every
            # robot's latency in that frame, and the monitor's arrival stamps, would carry it)
            gc.collect()
            gc.freeze()
            gc.disable()
            try:
                for stamp, msgs in prepared.frames:
                    if not cpu0 and stamp >= measured_from:
                        cpu0 = {name: _cpu_s(p.pid) for name, p in procs.items()}
                        cpu0["bench"] = _cpu_s(os.getpid())
                        threads0 = {name: _thread_cpu_s(p.pid) for name, p in procs.items()
                                    if name.startswith("backend")}
                        t_cpu0 = time.monotonic()
                    while (now := time.time_ns()) < stamp:
                        time.sleep(min(0.002, (stamp - now) * 1e-9))
                    if now - stamp > period_ns:
                        late += 1
                    for key, payload, cell in msgs:
                        pub = pubs.get(key)
                        if pub is None:
                            session = sessions[0 if cell < 0 else cell % n_routers]
                            pub = pubs[key] = session.declare_publisher(key, **qos)
                        pub.put(payload)
                    if cpu0 and msgs and msgs[0][2] >= 0:  # a camera frame, all sent
                        lag_ns.append(time.time_ns() - stamp)
            finally:
                gc.enable()
                gc.unfreeze()
            span_s = time.monotonic() - t_cpu0
            end_ns = time.time_ns()
            load1 = os.getloadavg()[0]
            cpu = {name: (_cpu_s(p.pid) - cpu0[name]) / span_s for name, p in procs.items()}
            cpu["bench"] = (_cpu_s(os.getpid()) - cpu0["bench"]) / span_s
            thread_cpu = {}
            for name, before in threads0.items():
                after = _thread_cpu_s(procs[name].pid)
                if before and after:
                    thread_cpu[name] = {c: (after[c] - before[c]) / span_s for c in before}
            time.sleep(2.5)  # the last poses, and a status with the final counters
        finally:
            for s in sessions:
                s.close()
    finally:
        stop_services(list(procs.values())[::-1])
    got: dict[tuple[str, int], list[int]] = {}
    for rx, robot, payload in poses:
        est = decode(payload)
        if isinstance(est, PoseEstimate) and "multi_frame" not in est.flags:
            got.setdefault((robot, est.stamp_ns), []).append(rx)
    expected = {fs for fs in prepared.seen if fs[1] >= measured_from}
    latencies = sorted((rid, (st - measured_from) * 1e-9, (rxs[0] - st) * 1e-6)
                       for (rid, st), rxs in got.items() if (rid, st) in expected)
    lat = np.array([ms for _, _, ms in latencies])
    counters: dict[str, int] = {}
    stage_ms: dict[str, float] = {}
    owners: dict[str, str] = {}
    received: dict[str, int] = {}
    # the backends' own stage latencies: the worst p99 any status of the measured span gave
    for st in history:
        if measured_from <= st.stamp_ns <= end_ns:
            for stage, ms in st.latency_p99_ms.items():
                stage_ms[stage] = max(stage_ms.get(stage, 0.0), float(ms))
    in_span = {inst: sum(1 for st in history if st.instance_id == inst
                         and measured_from <= st.stamp_ns <= end_ns) for inst in statuses}
    for inst, st in statuses.items():
        for name, v in st.counters.items():
            if name in DROP_COUNTERS or name.startswith(
                    ("ownership.", "standby.", "external_pose.used", "stale_dropped")):
                counters[name] = counters.get(name, 0) + int(v)
        owns = [part.split(":", 1)[1].strip() for part in st.detail.split(";")
                if part.strip().startswith("owns")]
        owners[inst] = owns[0] if owns else "?"
        received[inst] = int(st.counters.get("sync.received", 0))
    accounted = sum(v for k, v in counters.items() if k in DROP_COUNTERS)
    lost = sorted(expected - set(got), key=lambda fs: fs[1])
    missing = len(lost)
    missing_at = [(rid, round((st - measured_from) * 1e-9, 3)) for rid, st in lost[:8]]
    return RowResult(
        backends=n_backends, split=split,
        p50_ms=float(np.percentile(lat, 50)) if lat.size else math.nan,
        p99_ms=float(np.percentile(lat, 99)) if lat.size else math.nan,
        max_ms=float(lat.max()) if lat.size else math.nan,
        poses=int(lat.size), frame_sets=len(expected), missing=missing, accounted=accounted,
        duplicates=sum(1 for rxs in got.values() if len(rxs) > 1), late_publish=late, cpu=cpu,
        counters=counters, stage_ms=stage_ms, owners=owners,
        statuses_in_span=in_span, unreadable_statuses=bad_status[0], missing_at=missing_at,
        received=received, areas={k: ",".join(v) or "all" for k, v in served.items()},
        load1=load1,
        send_lag_ms=((float(np.percentile(lag_ns, 99)) * 1e-6, max(lag_ns) * 1e-6) if lag_ns
                     else (math.nan, math.nan)),
        thread_cpu=thread_cpu, latencies=latencies)


def _ratio(a: float, b: float) -> str:
    return f"{a / b:.2f}x" if b > 0 and math.isfinite(a) and math.isfinite(b) else "-"


def worst_frames(latencies: Sequence[tuple[str, float, float]], n: int = 5
                 ) -> list[tuple[float, float]]:
    """The ``n`` frame times (s into the span) whose slowest pose was slowest, with that
    latency (ms), in time order: a tail that comes back at the same moments of the traffic
    in every run is work the traffic triggers, not the host."""
    slowest: dict[float, float] = {}
    for _, t, ms in latencies:
        key = round(t, 3)
        slowest[key] = max(slowest.get(key, 0.0), ms)
    return sorted(sorted(slowest.items(), key=lambda kv: -kv[1])[:n])


def write_latencies(path: Path, rows: Sequence[RowResult]) -> None:
    """Every measured pose of ``rows`` as CSV: split, backends, robot, stamp (s into the
    span), latency (ms)."""
    with path.open("w") as f:
        f.write("split,backends,robot,stamp_s,latency_ms\n")
        for r in rows:
            for rid, t, ms in r.latencies:
                f.write(f"{r.split},{r.backends},{rid},{t:.3f},{ms:.3f}\n")


def print_row(r: RowResult, base: RowResult | None) -> None:
    ratio = (f"{_ratio(r.p50_ms, base.p50_ms):>7}{_ratio(r.p99_ms, base.p99_ms):>7}"
             if base is not None else f"{'':>14}")
    print(f"{r.split:>6}{r.backends:>9}{r.p50_ms:>9.1f}{r.p99_ms:>9.1f}{r.max_ms:>9.1f}{ratio}"
          f"{r.missing:>7}/{r.frame_sets:<6}{r.silent:>7}{r.duplicates:>6}{r.late_publish:>6}",
          flush=True)
    backends = sum(v for k, v in r.cpu.items() if k.startswith("backend"))
    routers = sum(v for k, v in r.cpu.items() if k.startswith("router"))
    print(f"{'':>8}CPU s/s: backends {backends:.2f} ("
          + ", ".join(f"{v:.2f}" for k, v in r.cpu.items() if k.startswith("backend"))
          + f"), routers {routers:.2f}, publisher+monitor {r.cpu['bench']:.2f}; machine load "
          f"average {r.load1:.1f} (1 min, {os.cpu_count()} cores); frames sent after their "
          f"stamp p99 {r.send_lag_ms[0]:.1f} ms, max {r.send_lag_ms[1]:.1f} ms")
    if r.thread_cpu:
        print(f"{'':>8}backend threads CPU s/s (worker / zenoh / other): " + "; ".join(
            f"{k.removeprefix('backend')} " + " / ".join(f"{v.get(c, math.nan):.2f}"
                                                        for c in THREAD_CLASSES)
            for k, v in sorted(r.thread_cpu.items())))
    worst = worst_frames(r.latencies)
    if worst:
        print(f"{'':>8}worst frames (s into the span: slowest pose ms): "
              + ", ".join(f"{t:.2f}: {ms:.0f}" for t, ms in worst))
    print(f"{'':>8}backend stage p99 ms: "
          + ", ".join(f"{k} {v:.1f}" for k, v in sorted(r.stage_ms.items())))
    print(f"{'':>8}counters: " + (", ".join(f"{k} {v}" for k, v in sorted(r.counters.items()))
                                  or "-"))
    print(f"{'':>8}owners: " + "; ".join(f"{k}: {v}" for k, v in sorted(r.owners.items())))
    print(f"{'':>8}areas and camera messages received: " + "; ".join(
        f"{k}: {r.areas.get(k, '?')} {r.received.get(k, 0)}" for k in sorted(r.owners)))
    print(f"{'':>8}statuses over the measured span: "
          + ", ".join(f"{k} {v}" for k, v in sorted(r.statuses_in_span.items()))
          + (f"; {r.unreadable_statuses} unreadable" if r.unreadable_statuses else ""))
    if r.missing_at:
        print(f"{'':>8}first missing (robot, s into the span): "
              + ", ".join(f"{rid} {t:.2f}" for rid, t in r.missing_at))


@dataclasses.dataclass
class CpuResult:
    """One backend's CPU in process (``--cpu-only``): the split, the areas it served, how many
    camera messages it was handed, and CPU seconds per second of traffic."""

    split: str
    backend: str
    areas: str
    camera_messages: int
    robots_run: int
    cpu_s_per_s: float
    #: the longest single message (decode, route, solve, fuse) in that half, ms: a stall every
    #: frame-set in the queue behind it waits for
    longest_message_ms: float = math.nan
    #: the longest tick with the idle upkeep after it (the backend's deferred marginalizations)
    longest_tick_ms: float = math.nan


def in_process_cpu(split: str, n_backends: int, n_routers: int, n_robots: int,
                   n_cameras: int, rate_hz: float, odom_rate_hz: float, seconds: float,
                   workdir: Path) -> list[CpuResult]:
    """Each backend's work without Zenoh and without the other processes: a
    :class:`~backend_service.service.BackendNode` per backend, handed the messages its
    subscriptions would receive (``area``: its areas' cameras; every robot's odometry and
    localization) in stamp order through the runtime's decode-and-dispatch, and running the
    robots the split would give it (``area``: those of its areas' cells; ``none``: the
    rendezvous hash over the backends). CPU time (``time.process_time``) over the second half
    of ``seconds`` of traffic: the figure does not depend on what else runs on the machine."""
    n_areas = n_routers if split == "area" else 0
    site, layout = write_fleet_site(workdir / "fleet_site_cpu.yaml", n_robots, n_cameras,
                                    n_areas)
    prepared = prepare_run(site, layout, rate_hz, odom_rate_hz, seconds,
                           np.random.default_rng(0))
    names = [f"b{b}" for b in range(n_backends)]
    out = []
    quiet = logging.getLogger("backend_service")
    level = quiet.level
    quiet.setLevel(logging.WARNING)  # each node logs the robots it does not run
    try:
        for b in range(len(names)):
            out.append(_one_backend_cpu(site, layout, prepared, split, b, names, n_areas,
                                        seconds))
    finally:
        quiet.setLevel(level)
    return out


def _one_backend_cpu(site: Site, layout: FleetLayout, prepared: PreparedRun, split: str,
                     b: int, names: list[str], n_areas: int, seconds: float) -> CpuResult:
    from backend_service.ownership import choose_owner
    from backend_service.service import BackendNode
    from core.runtime import ScriptedRunner, dispatch

    name = names[b]
    areas = backend_areas_of(b, len(names), len(site.section("areas"))) if n_areas else []
    node = BackendNode(site, name, areas=areas)
    if areas:
        served = {int(a[1:]) for a in areas}
        robots = [r for i, r in enumerate(layout.robot_ids) if i % n_areas in served]
    else:
        robots = [r for r in layout.robot_ids if choose_owner(r, names) == name]
    node.pipeline.set_active(robots)
    runner = ScriptedRunner(node)
    subs: dict[str, Any] = {}
    half_ns = prepared.start_ns + round(seconds * 0.5e9)
    cpu0: float | None = None
    cams = 0
    longest_message = longest_tick = 0.0
    clock = time.perf_counter
    for stamp, msgs in prepared.frames:
        if cpu0 is None and stamp >= half_ns:
            cpu0 = time.process_time()
        recv_ns = stamp + 2_000_000
        t = clock()
        runner.tick(recv_ns)  # the tick, then the idle upkeep
        if cpu0 is not None:
            longest_tick = max(longest_tick, clock() - t)
        for key, payload, _cell in msgs:
            if key not in subs:
                subs[key] = runner._match(key)
            sub = subs[key]
            if sub is None:
                continue  # not subscribed: Zenoh would not deliver it
            if cpu0 is not None and sub.message_type is RobotDetections:
                cams += 1
            t = clock()
            dispatch(node, sub, key, payload, recv_ns)
            if cpu0 is not None:
                longest_message = max(longest_message, clock() - t)
    cpu = time.process_time() - (cpu0 or 0.0)
    return CpuResult(split, name, ",".join(areas) or "all", cams, len(robots),
                     cpu / (seconds * 0.5), longest_message * 1e3, longest_tick * 1e3)


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench fleet", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--robots", type=int, default=10, help="robots (one cell each)")
    parser.add_argument("--cameras", type=int, default=100, help="cameras in all")
    parser.add_argument("--rate", type=float, default=15.0, help="camera frames per second")
    parser.add_argument("--odom-rate", type=float, default=20.0,
                        help="each robot's odometry messages per second")
    parser.add_argument("--backends", default="1,2,3",
                        help="comma-separated backend counts: one row each")
    parser.add_argument("--routers", type=int, default=3, help="routers in a chain")
    parser.add_argument("--seconds", type=float, default=10.0, help="measured time per row")
    parser.add_argument("--split", default="none,area",
                        help="comma-separated ways to split the facility over the backends: "
                        "none (every backend receives every camera), area (each backend the "
                        "cameras of its routers' areas); one set of rows each")
    parser.add_argument("--warmup", type=float, default=30.0,
                        help="unmeasured start per row: ownership settles, robots localize, "
                        "and every robot's pose graph fills its window (200 keyframes, about "
                        "13 s at 15 Hz) and has marginalized a few times, so the row measures "
                        "a backend as it runs for hours "
                        "(its marginalizations included); a shorter warm-up measures a young "
                        "backend")
    parser.add_argument("--latencies", type=Path, metavar="CSV",
                        help="write every measured pose's latency (split, backends, robot, "
                        "stamp s into the span, ms) to this CSV file")
    parser.add_argument("--cpu-only", action="store_true",
                        help="no processes, no Zenoh: each backend's CPU per second of traffic "
                        "in this process, per split and backend count (independent of the "
                        "machine's other load)")
    args = parser.parse_args(list(argv))
    try:
        counts = [int(v) for v in args.backends.split(",")]
    except ValueError:
        parser.error(f"--backends: comma-separated integers, got {args.backends!r}")
    if any(c < 1 for c in counts) or args.routers < 1 or args.rate <= 0 or args.seconds <= 0:
        parser.error("--backends, --routers, --rate and --seconds must be positive")
    splits = [v.strip() for v in args.split.split(",") if v.strip()]
    if not splits or any(v not in SPLITS for v in splits):
        parser.error(f"--split: comma-separated of {', '.join(SPLITS)}, got {args.split!r}")
    print(f"machine: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}")
    print(f"{args.robots} robots, {args.cameras} cameras at {args.rate:g} Hz, odometry "
          f"{args.odom_rate:g} Hz, {args.routers} routers in a chain, {args.seconds:g} s "
          f"measured per row after {args.warmup:g} s")
    if args.cpu_only:
        print(f"{'split':>6}{'backends':>9}  backend  areas     camera msgs  robots  CPU s/s"
              f"  longest msg / tick ms")
        with tempfile.TemporaryDirectory(prefix="smartedge-bench-fleet-") as tmp:
            for split in splits:
                for b in counts:
                    res = in_process_cpu(split, b, args.routers, args.robots, args.cameras,
                                         args.rate, args.odom_rate, args.seconds, Path(tmp))
                    for r in res:
                        print(f"{split:>6}{b:>9}  {r.backend:<8} {r.areas:<9}"
                              f"{r.camera_messages:>12}{r.robots_run:>8}{r.cpu_s_per_s:>9.3f}"
                              f"{r.longest_message_ms:>11.1f} / {r.longest_tick_ms:.1f}",
                              flush=True)
                    print(f"{'':>15}sum {sum(r.cpu_s_per_s for r in res):.3f} s/s, busiest "
                          f"{max(r.cpu_s_per_s for r in res):.3f} s/s", flush=True)
        print("CPU s/s: CPU seconds of the backend per second of traffic (second half of "
              "--seconds); camera msgs: camera messages it was handed in that half; longest "
              "msg / tick: the longest single message and the longest tick with its idle "
              "upkeep in that half (a pose graph's window fills after about 13 s at 15 Hz: "
              "--seconds 40 shows its marginalizations)")
        return 0
    rows: list[RowResult] = []
    with tempfile.TemporaryDirectory(prefix="smartedge-bench-fleet-") as tmp:
        for split in splits:
            first: RowResult | None = None
            for b in counts:
                print(f"row: split {split}, {b} backend(s)", flush=True)
                r = run_row(FleetRow(b, args.routers, args.robots, args.cameras, args.rate,
                                     args.odom_rate, args.seconds, args.warmup, split=split),
                            Path(tmp))
                if not rows:
                    print(f"{'split':>6}{'backends':>9}{'p50 ms':>9}{'p99 ms':>9}{'max ms':>9}"
                          f"{'p50 x':>7}{'p99 x':>7}{'missing':>14}{'silent':>7}{'dup':>6}"
                          f"{'late':>6}")
                print_row(r, first)
                first = first or r
                rows.append(r)
    if args.latencies is not None:
        write_latencies(args.latencies, rows)
        print(f"latencies of {sum(len(r.latencies) for r in rows)} poses: {args.latencies}")
    if len(splits) > 1:
        print("side by side (p50 / p99 ms, CPU of the backends s/s; ratio area / none):")
        by = {(r.split, r.backends): r for r in rows}
        for b in counts:
            cells = []
            for split in splits:
                r = by[(split, b)]
                cpu = sum(v for k, v in r.cpu.items() if k.startswith("backend"))
                cells.append(f"{split} {r.p50_ms:.1f} / {r.p99_ms:.1f} ms, {cpu:.2f} s/s, "
                             f"missing {r.missing}/{r.frame_sets}")
            line = f"  {b} backend(s): " + "; ".join(cells)
            if ("none", b) in by and ("area", b) in by:
                a, n = by[("area", b)], by[("none", b)]
                line += (f"; area/none p50 {_ratio(a.p50_ms, n.p50_ms)}, p99 "
                         f"{_ratio(a.p99_ms, n.p99_ms)}")
            print(line)
    print("latency: frame-set stamp -> the robot's camera pose received on the last router; "
          "p50 x/p99 x: vs the split's first row; missing: frame-sets (robot seen by a camera) "
          "with no pose; silent: missing beyond the backends' drop counters (shed, "
          "stale_dropped.camera_pose, sync overflow/late/rate-limited, no_estimate, "
          "ownership.withheld, unassigned detections); "
          "dup: poses received twice (two publishers); late: frames this publisher sent "
          "more than one period late; backend threads: the worker, Zenoh's runtime, the rest "
          "(callback threads, numpy's BLAS)")
    return 0 if all(r.silent == 0 and r.duplicates == 0 for r in rows) else 1
