"""``smartedge evaluate paper --jobs``: the independent runs of experiment 1 in worker
processes give the tables of the serial run, number for number (each run's seed follows from
its plan, never from the process or the order it ran in), and what the workers need crosses
the process boundary (a scenario's site holds read-only mappings)."""

from __future__ import annotations

import dataclasses
import pickle
from pathlib import Path

import numpy as np
import pytest

from lab.experiments import PaperConfig, run_paper
from lab.experiments.parallel import dumps_portable, resolve_jobs
from simulation.scenario import load_scenario

#: what each run writes that depends only on its numbers (report.md holds the wall time)
RESULT_FILES = ("results.json", "table1.md", "table2.md", "nees.md", "samples.csv")


@pytest.fixture(scope="module")
def serial_and_parallel(tmp_path_factory: pytest.TempPathFactory):
    cfg = PaperConfig(runs_per_direction=1, trajectories=("traj3",), stop_s=2.0,
                      experiments=(1,), camera_rate_hz=5.0)
    out = {}
    for jobs in (1, 2):
        folder = tmp_path_factory.mktemp(f"jobs{jobs}")
        lines: list[str] = []
        report = run_paper(dataclasses.replace(cfg, jobs=jobs), folder, progress=lines.append)
        out[jobs] = (report, lines, folder)
    return out


def test_jobs_2_writes_the_tables_of_jobs_1(serial_and_parallel) -> None:
    (_, lines1, one), (_, lines2, two) = serial_and_parallel[1], serial_and_parallel[2]
    assert any("2 processes" in ln for ln in lines2) and not any("processes" in ln
                                                                 for ln in lines1)
    for name in RESULT_FILES:
        assert (Path(one) / name).read_bytes() == (Path(two) / name).read_bytes(), name
    tum_one = sorted(p.relative_to(one) for p in Path(one).glob("tum/*/*.tum"))
    assert tum_one == sorted(p.relative_to(two) for p in Path(two).glob("tum/*/*.tum"))
    assert len(tum_one) >= 2 * 3
    for rel in tum_one:
        assert (Path(one) / rel).read_bytes() == (Path(two) / rel).read_bytes(), rel


def test_jobs_2_returns_the_runs_of_jobs_1_in_plan_order(serial_and_parallel) -> None:
    runs1 = serial_and_parallel[1][0].accuracy_runs
    runs2 = serial_and_parallel[2][0].accuracy_runs
    assert [r.name for r in runs1] == [r.name for r in runs2] == ["traj3_1", "traj3r_1"]
    for a, b in zip(runs1, runs2, strict=True):
        np.testing.assert_array_equal(a.fused, b.fused)
        np.testing.assert_array_equal(a.robot, b.robot)
        assert a.counters == b.counters
        assert [s.estimates.keys() for s in a.samples] == [s.estimates.keys() for s in b.samples]
        for sa, sb in zip(a.samples, b.samples, strict=True):
            for key, est in sa.estimates.items():
                np.testing.assert_array_equal(est, sb.estimates[key])


def test_a_scenario_crosses_the_process_boundary() -> None:
    sc = load_scenario()
    back = pickle.loads(dumps_portable(sc))
    assert back.name == sc.name and sorted(back.site.cameras) == sorted(sc.site.cameras)
    assert dict(back.site.sections) == dict(sc.site.sections)
    np.testing.assert_array_equal(back.site.cameras["cam1"].T_cam_world,
                                  sc.site.cameras["cam1"].T_cam_world)


def test_jobs_resolution() -> None:
    assert resolve_jobs(4, 2) == 2  # never more processes than runs
    assert resolve_jobs(1, 18) == 1
    assert resolve_jobs(None, 1) == 1
    assert resolve_jobs(3, 18) == 3
    # something that cannot reach a worker (a lambda) keeps the runs in this process
    assert resolve_jobs(2, 18, (lambda robot_id: None,)) == 1
    with pytest.raises(ValueError, match="jobs"):
        PaperConfig(jobs=0)
