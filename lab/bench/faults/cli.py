"""``smartedge bench reliability``: hostile and faulty input against the running system.

Every probe starts the real services as OS processes on Zenoh loopback, the way ``smartedge
demo --processes`` does (backend, four simulated edge agents with the detection noise model,
the robot bridge on the simulated HSR; no viewer, no clouds), lets the simulated robot drive
the paper site's ``traj3``, injects one fault from a separate *attacker* Zenoh session (or
kills a process), and measures what the system did against the simulator's ground truth:
crashes, the services' counters and status, the backend's resident memory (``/proc``), camera
pose rate and error, fused error, the robot's own localization error, corrections pushed, and
recovery times. One Markdown table row per probe: probe, the figure the first fault survey
measured before the fixes (docs/reliability.md), the figures now, the verdict against what
must hold (``--list`` prints the probes).

The ``baseline`` probe runs the same system without a fault; the other probes compare their
fault window with the same window of the baseline run (same trajectory, same seed), or with
their own pre-fault window when the baseline was not run.

The loopback peers have no TLS, so the router's access control (the identity mechanism,
docs/deployment.md) is not in the loop: a probe that poses as the backend measures the robot
bridge's own defences only.
"""

from __future__ import annotations

import argparse
import dataclasses
import math
import os
import platform
import subprocess
import time
from collections.abc import Sequence
from pathlib import Path

from lab.bench.faults.harness import STARTUP_S, TRAJECTORY, Probe, Run, Verdict
from lab.bench.faults.probes import PROBES


@dataclasses.dataclass
class Row:
    """One table row."""

    probe: Probe
    verdict: Verdict

    def markdown(self) -> str:
        p, v = self.probe, self.verdict
        return (f"| `{p.name}`: {p.sends} | {p.before} | {'; '.join(v.figures)} | "
                f"{'pass' if v.ok else 'FAIL'}: {p.holds} |")


def run_probes(names: Sequence[str], seconds: float | None, out_dir: Path,
               progress_s: float = 10.0, startup_s: float = STARTUP_S) -> list[Row]:
    """Run the probes ``names`` (in catalogue order, so the baseline first when named) and
    judge them; ``seconds``: simulated seconds observed per probe (default: each probe's own);
    ``startup_s``: between starting the services and the simulation's t = 0."""
    rows: list[Row] = []
    reference: Run | None = None
    order = sorted(names, key=lambda n: list(PROBES).index(n))
    for name in order:
        probe = PROBES[name]
        run = Run(probe, seconds or probe.run_s, out_dir, startup_s)
        run.execute(progress_s)
        try:
            verdict = probe.judge(run, reference if name != "baseline" else None)
        except Exception as exc:  # a judging bug must not lose the other rows
            verdict = Verdict([f"judging failed: {type(exc).__name__}: {exc}"], False)
        if name == "baseline":
            reference = run
        row = Row(probe, verdict)
        rows.append(row)
        print(f"[{name}] {'pass' if verdict.ok else 'FAIL'}: {'; '.join(verdict.figures)}",
              flush=True)
    return rows


def _code_version() -> str:
    """The git commit of the code under test, ``+changes`` when tracked files differ from it
    (``unknown`` outside a git checkout)."""
    here = Path(__file__).resolve().parent
    try:
        sha = subprocess.run(["git", "rev-parse", "--short", "HEAD"], cwd=here, check=True,
                             capture_output=True, text=True, timeout=10).stdout.strip()
        dirty = subprocess.run(["git", "status", "--porcelain", "--untracked-files=no"],
                               cwd=here, check=True, capture_output=True, text=True,
                               timeout=10).stdout.strip()
    except (OSError, subprocess.SubprocessError):
        return "unknown"
    return sha + ("+changes" if dirty else "")


def main(argv: Sequence[str]) -> int:
    parser = argparse.ArgumentParser(prog="smartedge bench reliability", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--probes", default=",".join(PROBES),
                        help="comma-separated probe names (default: all; --list names them)")
    parser.add_argument("--list", action="store_true",
                        help="print each probe's name, what it sends and what must hold; exit")
    parser.add_argument("--seconds", type=float,
                        help="observe each probe for this many seconds of simulated time (the "
                        "fault window scaled to it; default: each probe's own, 25-76 s)")
    parser.add_argument("--out", default="runs/reliability", help="folder for the service logs")
    parser.add_argument("--progress-s", type=float, default=10.0, help="progress line period")
    parser.add_argument("--startup-s", type=float, default=STARTUP_S,
                        help="seconds between starting the services and the simulation's t = 0 "
                        f"(default {STARTUP_S:g})")
    args = parser.parse_args(list(argv))
    if args.list:
        for probe in PROBES.values():
            print(f"{probe.name}: {probe.summary}")
        return 0
    chosen = [n.strip() for n in args.probes.split(",") if n.strip()]
    unknown = [n for n in chosen if n not in PROBES]
    if unknown or not chosen:
        parser.error(f"unknown probe(s) {unknown}; choose from {','.join(PROBES)}")
    out_dir = Path(args.out)
    out_dir.mkdir(parents=True, exist_ok=True)
    load = os.getloadavg()[0] if hasattr(os, "getloadavg") else math.nan
    print(f"smartedge bench reliability: {platform.machine()}, {os.cpu_count()} cores, python "
          f"{platform.python_version()}, load {load:.1f}, code {_code_version()}, "
          f"{time.strftime('%Y-%m-%d %H:%M %Z')}; services as processes on Zenoh "
          f"loopback (no TLS, no router ACL), {TRAJECTORY}, detection noise model; logs in "
          f"{out_dir}", flush=True)
    t0 = time.monotonic()
    rows = run_probes(chosen, args.seconds, out_dir, args.progress_s, args.startup_s)
    print(f"\n{len(rows)} probes in {time.monotonic() - t0:.0f} s\n")
    print("| probe | before the fixes | now | verdict |")
    print("|---|---|---|---|")
    for row in rows:
        print(row.markdown())
    return 0 if all(r.verdict.ok for r in rows) else 1


__all__ = ["Row", "main", "run_probes"]
