"""The fault harness, ``smartedge bench reliability``: hostile and faulty input against the
running services, one verdict per probe (figures in docs/reliability.md).

- :mod:`.harness`: the services as OS processes on Zenoh loopback, the attacker session, the
  monitor, and the figures a judge asks for (:class:`~.harness.Run`);
- :mod:`.probes`: the catalogue (:data:`~.probes.PROBES`), one named probe per fault with what
  it sends and what must hold;
- :mod:`.cli`: the command (``--probes NAME,...``, ``--list``).
"""

from __future__ import annotations

from smartedge.bench.faults.cli import Row, main, run_probes
from smartedge.bench.faults.harness import Probe, Run, Verdict
from smartedge.bench.faults.probes import PROBES

__all__ = ["PROBES", "Probe", "Row", "Run", "Verdict", "main", "run_probes"]
