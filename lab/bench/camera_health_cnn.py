"""The camera-health monitor on the shipped CNN's keypoints (``smartedge bench camera-health
--detections cnn``).

The noise-model benchmark (:mod:`lab.bench.camera_health`) draws every frame's keypoint
error afresh. A CNN's error belongs to the view: a standing or creeping robot shows a camera
nearly the same error frame after frame, which a monitor counting frames as independent takes
for a bump. This benchmark renders runs of the paper lab's trajectories (each forward and
reversed, per seed) through the shipped ONNX models (:mod:`lab.rendered_detections`,
5 frames/s per camera, what the closed-loop demo runs) once, then replays the detections through
:class:`~backend_service.pipeline.BackendPipeline` with the monitor set two ways in the same run:
as the site sets it (views weighed by how far the robot moved since the camera's previous one)
and the peer that counts every frame (``independent_motion_m`` / ``independent_turn_deg`` near
0). Figures per setting:

- **false alarms**: runs in which an unmoved camera was named (``action: report``), cameras
  named, and the largest test statistic against the alarm threshold;
- **bumps**: each camera of ``--bump-cameras`` in turn given a calibration off by a 5 cm / 1 deg
  bump (its true pose stays; what the monitor sees is the same as the camera having moved
  before the run), named in how many runs, after how many seconds of the robot in its view
  (mean, max), and runs in which another camera was named.
"""

from __future__ import annotations

import dataclasses
import time
from collections.abc import Callable, Sequence
from typing import Final

import numpy as np

from backend_service.camera_health import CameraHealthConfig
from backend_service.pipeline import BackendPipeline
from backend_service.pipeline_config import PipelineConfig
from core.site import Site
from protocol.messages import Message, RobotDetections
from simulation.detections import CameraBump
from simulation.runner import SimulationRun
from simulation.scenario import Scenario, load_scenario

#: frames per second per camera (the closed-loop demo's ``--render-rate``)
RATE_HZ: Final = 5.0
#: localization rate of the runs (the robot bridge's)
LOCALIZATION_RATE_HZ: Final = 10.0
#: the bump the calibration is off by: 5 cm / 1 deg, world axes, not along one axis
BUMP_T_M: Final = (0.03, 0.04, 0.0)
BUMP_R_DEG: Final = (0.0, 0.6, 0.8)
#: the peer: every frame counted as an independent view
EVERY_FRAME: Final = {"independent_motion_m": 1e-9, "independent_turn_deg": 1e-9}

Run = tuple[str, list[tuple[Message, int]]]


def render_runs(scenario: Scenario, seeds: Sequence[int], trajectories: Sequence[str],
                say: Callable[[str], None]) -> list[Run]:
    """(name, [(message, arrival ns)]) of every trajectory, forward and reversed, per seed,
    the detections rendered and inferred once."""
    from lab.experiments.config import PaperConfig, make_detector
    from simulation.world import World

    sc = scenario.with_overrides(cameras=dataclasses.replace(scenario.cameras,
                                                             rate_hz=RATE_HZ))
    world = World(sc)
    detector = make_detector(sc, world, PaperConfig(detections="cnn"))
    out: list[Run] = []
    for seed in seeds:
        for traj in trajectories:
            for reverse in (False, True):
                t0 = time.perf_counter()
                sim = SimulationRun(sc, traj, reverse, seed=seed, world=world,
                                    detector=detector)
                msgs = [(tm.message, tm.arrival_ns)
                        for tm in sim.messages(localization_rate_hz=LOCALIZATION_RATE_HZ)]
                name = f"{traj}{'r' if reverse else ''}/{seed}"
                out.append((name, msgs))
                say(f"  rendered {name}: {sim.duration_s:.0f} s simulated, "
                    f"{sum(isinstance(m, RobotDetections) for m, _ in msgs)} camera frames "
                    f"in {time.perf_counter() - t0:.0f} s")
    return out


@dataclasses.dataclass
class Replay:
    """One run replayed: cameras ``named`` (id -> seconds of the robot in that camera's view
    before its naming), ``max_chi2`` per camera (the largest over the run)."""

    named: dict[str, float] = dataclasses.field(default_factory=dict)
    max_chi2: dict[str, float] = dataclasses.field(default_factory=dict)


def replay(site: Site, msgs: Sequence[tuple[Message, int]], health: CameraHealthConfig
           ) -> Replay:
    """``msgs`` through a pipeline with ``health`` (``action: report``)."""
    config = PipelineConfig.from_site(site)
    config = dataclasses.replace(config, camera_health=dataclasses.replace(health,
                                                                           action="report"))
    pipeline = BackendPipeline(site, config)
    monitor = pipeline.camera_health
    out = Replay()
    visible: dict[str, float] = {}
    for msg, arrival_ns in msgs:
        pipeline.step(msg, arrival_ns)
        if not isinstance(msg, RobotDetections):
            continue
        if msg.detections:
            visible[msg.camera_id] = visible.get(msg.camera_id, 0.0) + 1.0 / RATE_HZ
        st = monitor.state(msg.camera_id)
        if st is not None:
            out.max_chi2[msg.camera_id] = max(out.max_chi2.get(msg.camera_id, 0.0), st.chi2)
        for cid in monitor.moved:
            out.named.setdefault(cid, visible.get(cid, 0.0))
    return out


def miscalibrated(site: Site, camera_id: str) -> Site:
    """``site`` with ``camera_id``'s calibration off by the inverse of the 5 cm / 1 deg bump
    (the camera as if it had moved by the bump)."""
    bump = CameraBump(camera_id, 0, tuple(-v for v in BUMP_T_M),
                      tuple(-v for v in BUMP_R_DEG))
    cameras = dict(site.cameras)
    cameras[camera_id] = bump.apply(cameras[camera_id])
    return dataclasses.replace(site, cameras=cameras)


def run(seeds: Sequence[int], trajectories: Sequence[str], bump_cameras: Sequence[str],
        say: Callable[[str], None] = print) -> dict[str, dict[str, float]]:
    """Render once, replay both settings; prints the table and returns its figures."""
    scenario = load_scenario()
    site = scenario.site
    for cid in bump_cameras:
        if cid not in site.cameras:
            raise SystemExit(f"--bump-cameras: {cid!r} is not a camera of "
                             f"{site.source_path}; it has {sorted(site.cameras)}")
    say(f"rendering {len(seeds) * len(trajectories) * 2} runs of the paper lab through the "
        f"shipped models ({RATE_HZ:g} frames/s per camera)")
    runs = render_runs(scenario, seeds, trajectories, say)
    base = CameraHealthConfig.from_site(site)
    settings = {"views weighed by motion (site)": base,
                "every frame counted (peer)": dataclasses.replace(base, **EVERY_FRAME)}
    figures: dict[str, dict[str, float]] = {}
    for label, health in settings.items():
        t0 = time.perf_counter()
        alarm_runs = 0
        alarms = 0
        max_chi2 = 0.0
        for _, msgs in runs:
            r = replay(site, msgs, health)
            alarm_runs += bool(r.named)
            alarms += len(r.named)
            max_chi2 = max([max_chi2, *r.max_chi2.values()])
        named_after: list[float] = []
        wrong = 0
        trials = 0
        for cid in bump_cameras:
            bumped = miscalibrated(site, cid)
            for _, msgs in runs:
                trials += 1
                r = replay(bumped, msgs, health)
                if cid in r.named:
                    named_after.append(r.named[cid])
                wrong += any(c != cid for c in r.named)
        row = {"runs": float(len(runs)), "alarm_runs": float(alarm_runs),
               "alarms": float(alarms), "max_chi2": max_chi2,
               "bumps": float(trials), "bumps_named": float(len(named_after)),
               "named_mean_s": float(np.mean(named_after)) if named_after else float("nan"),
               "named_max_s": float(np.max(named_after)) if named_after else float("nan"),
               "wrong_camera_runs": float(wrong), "replay_s": time.perf_counter() - t0}
        figures[label] = row
    say("")
    say(f"camera health on the shipped CNN's keypoints: {len(runs)} runs "
        f"({', '.join(trajectories)}, forward and reversed, seeds {list(seeds)}), alarm at "
        f"chi2 {base.alarm_chi2:g}; bumps of 5 cm / 1 deg of {', '.join(bump_cameras)}")
    say("| monitor | runs with a false alarm | cameras named | largest chi2 of an unmoved "
        "camera | bumps named | robot in view before naming, mean / max s | runs naming "
        "another camera |")
    say("|---|---|---|---|---|---|---|")
    for label, row in figures.items():
        say(f"| {label} | {row['alarm_runs']:.0f} / {row['runs']:.0f} | {row['alarms']:.0f} | "
            f"{row['max_chi2']:.1f} | {row['bumps_named']:.0f} / {row['bumps']:.0f} | "
            f"{row['named_mean_s']:.1f} / {row['named_max_s']:.1f} | "
            f"{row['wrong_camera_runs']:.0f} |")
    return figures
