"""The fault harness, ``smartedge bench reliability``: hostile and faulty input against the
running services, one verdict per probe (figures in docs/reliability.md).

- :mod:`.harness`: the services as OS processes on Zenoh loopback, the attacker session, the
  monitor, and the figures a judge asks for (:class:`~.harness.Run`);
- :mod:`.probes`: the catalogue (:data:`~.probes.PROBES`), one named probe per fault with what
  it sends and what must hold;
- :mod:`.cli`: the command (``--probes NAME,...``, ``--list``).

Part of the lab wing: may import every other package.
"""

from __future__ import annotations

from lab.bench.faults.cli import Row, main, run_probes
from lab.bench.faults.harness import Probe, Run, Verdict
from lab.bench.faults.probes import PROBES

__all__ = ["PROBES", "Probe", "Row", "Run", "Verdict", "main", "run_probes"]
