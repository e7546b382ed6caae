"""Shared fixtures: repository paths, the example site, loopback Zenoh sessions.

The process helpers (:func:`free_port`, :func:`stop_process`) are the project's own, from
:mod:`lab.launcher`, re-exported here for the tests."""

from __future__ import annotations

import os
import shutil
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest

from lab.launcher import free_port, stop_process  # noqa: F401 (re-exported)
from tests.machine_share import LOCK_DIR_ENV, make_lock_dir, worker_lock

REPO_ROOT = Path(__file__).resolve().parents[1]
EXAMPLE_SITE = REPO_ROOT / "deploy" / "site.example.yaml"


#: the controller's lock folder (removed when the run ends)
_LOCK_DIR = pytest.StashKey[Path]()


def pytest_configure(config: pytest.Config) -> None:
    """In the controller of a parallel run: the folder of the machine lock its workers share
    (:mod:`tests.machine_share`), made before the workers start."""
    parallel = bool(getattr(config.option, "numprocesses", None))
    if parallel and not hasattr(config, "workerinput") and LOCK_DIR_ENV not in os.environ:
        config.stash[_LOCK_DIR] = make_lock_dir()


def pytest_unconfigure(config: pytest.Config) -> None:
    folder = config.stash.get(_LOCK_DIR, None)
    if folder is not None:
        shutil.rmtree(folder, ignore_errors=True)
        os.environ.pop(LOCK_DIR_ENV, None)


@pytest.hookimpl(hookwrapper=True)
def pytest_runtest_protocol(item: pytest.Item, nextitem: pytest.Item | None) -> Iterator[None]:
    """Setup, call and teardown of a test hold the machine lock: shared, or alone for a test
    marked ``exclusive`` (real-time end-to-end figures)."""
    lock = worker_lock() if hasattr(item.config, "workerinput") else None
    if lock is None:
        yield
        return
    with lock.hold(exclusive=item.get_closest_marker("exclusive") is not None):
        yield


def wait_until(predicate: Callable[[], bool], timeout_s: float = 5.0, step_s: float = 0.02) -> bool:
    """Poll ``predicate`` until it is true or ``timeout_s`` passes; returns its last value."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if predicate():
            return True
        time.sleep(step_s)
    return bool(predicate())


@pytest.fixture
def example_site_path() -> Path:
    return EXAMPLE_SITE


@pytest.fixture
def example_site():
    from core.site import load_site

    return load_site(EXAMPLE_SITE)


#: simulated seconds of :func:`traj1_stream`
TRAJ1_STREAM_S = 40.0


@pytest.fixture(scope="session")
def traj1_stream():
    """(scenario, messages): the first 40 s of the paper's traj1 (seed 7) in arrival order,
    the robot's own localization at the rate the robot bridge publishes it; shared by the
    pipeline tests (frozen messages: nobody changes them)."""
    from robot_bridge.service import LOCALIZATION_PERIOD_NS
    from simulation.runner import SimulationRun
    from simulation.scenario import load_scenario

    scenario = load_scenario()
    sim = SimulationRun(scenario, "traj1", seed=7)
    return scenario, list(sim.messages(until_s=TRAJ1_STREAM_S,
                                       localization_rate_hz=1e9 / LOCALIZATION_PERIOD_NS))


@pytest.fixture
def zenoh_pair() -> Iterator[tuple[object, object, str]]:
    """Two real Zenoh peer sessions on loopback (scouting off): (listener, connector, endpoint)."""
    zenoh = pytest.importorskip("zenoh")
    from core.session import loopback_config

    endpoint = f"tcp/127.0.0.1:{free_port()}"
    a = zenoh.open(loopback_config(listen=[endpoint]))
    b = zenoh.open(loopback_config(connect=[endpoint]))
    try:
        yield a, b, endpoint
    finally:
        b.close()
        a.close()


# the tiny trained detector + keypoint models (session-scoped), for tests outside edge_agent/
from tests.edge_agent.conftest import tiny_models  # noqa: E402, F401
