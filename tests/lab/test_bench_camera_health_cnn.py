"""The CNN camera-health benchmark's replay (``smartedge bench camera-health --detections
cnn``): a calibration off by the bump is named, the right camera only.
Detections from the noise model here (the rendering is the benchmark's and the render tests'
business); the replay and the miscalibration are what is checked."""

from __future__ import annotations

import dataclasses

from backend_service.camera_health import CameraHealthConfig
from lab.bench.camera_health_cnn import EVERY_FRAME, RATE_HZ, miscalibrated, replay
from simulation.runner import SimulationRun
from simulation.scenario import load_scenario


def test_replay_names_the_miscalibrated_camera_only() -> None:
    sc = load_scenario()
    sc = sc.with_overrides(cameras=dataclasses.replace(sc.cameras, rate_hz=RATE_HZ))
    msgs = [(tm.message, tm.arrival_ns)
            for tm in SimulationRun(sc, "traj2", seed=3).messages(localization_rate_hz=10.0)]
    health = CameraHealthConfig.from_site(sc.site)
    bumped = replay(miscalibrated(sc.site, "cam3"), msgs,
                    dataclasses.replace(health, **EVERY_FRAME))
    assert set(bumped.named) == {"cam3"}
    assert 0 < bumped.named["cam3"] < 91.0  # seconds of the robot in cam3's view
    assert set(bumped.max_chi2) == set(sc.site.cameras)
    assert bumped.max_chi2["cam3"] >= health.alarm_chi2
