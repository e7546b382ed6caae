"""``smartedge bench sim``: simulated seconds per wall second on the paper site.

Generates every message of the paper's trajectory runs (4 cameras at 15 Hz, odometry at
20 Hz) through :class:`simulation.runner.SimulationRun` and reports the real-time factor of the
simulation alone and, with ``--with-backend``, of the simulation plus the backend pieces the
paper evaluation runs (synchronizer on every message, pose solves at the waypoints).
"""

from __future__ import annotations

import argparse
import platform
import sys
import time
from collections.abc import Sequence

from simulation.runner import SimulationRun, run_seed
from simulation.scenario import PAPER_SCENARIO, load_scenario


def main(argv: Sequence[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench sim", description=__doc__)
    parser.add_argument("--scenario", default=str(PAPER_SCENARIO))
    parser.add_argument("--runs", type=int, default=1,
                        help="iterations per trajectory and direction (default 1)")
    parser.add_argument("--with-backend", action="store_true",
                        help="also time the paper evaluation pipeline (sync, solver, fusion)")
    args = parser.parse_args(list(sys.argv[1:] if argv is None else argv))
    scenario = load_scenario(args.scenario)
    print(f"machine: {platform.machine()} {platform.processor() or ''} python "
          f"{platform.python_version()}")
    sim_s = wall_s = 0.0
    n_msgs = 0
    for name in scenario.trajectories:
        for reverse in (False, True):
            for it in range(args.runs):
                t0 = time.perf_counter()
                run = SimulationRun(scenario, name, reverse,
                                    seed=run_seed(scenario, name, reverse, it))
                for _ in run.messages():
                    n_msgs += 1
                wall_s += time.perf_counter() - t0
                sim_s += run.duration_s
    print(f"simulation only: {sim_s:.0f} simulated s in {wall_s:.2f} wall s = "
          f"{sim_s / wall_s:.1f}x real time ({n_msgs / wall_s:.0f} messages/s)")
    if args.with_backend:
        import tempfile

        from lab.experiments import PaperConfig, run_paper

        with tempfile.TemporaryDirectory() as tmp:
            rep = run_paper(PaperConfig(runs_per_direction=args.runs), tmp,
                            progress=lambda _line: None, scenario=scenario)
        total = sum(r.simulated_s for r in rep.accuracy_runs)
        print(f"paper pipeline: {total:.0f} simulated s in {rep.wall_s:.2f} wall s = "
              f"{total / rep.wall_s:.1f}x real time (fusion "
              f"{'on' if rep.fusion_available else 'off'})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
