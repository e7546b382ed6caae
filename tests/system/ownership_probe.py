"""A backend stand-in for the failover tests: the ownership logic on the real runner, no pipeline.

:class:`OwnershipProbe` is a ``backend`` :class:`~core.runtime.ServiceNode` wired the way
``smartedge backend`` is to use backend_service/ownership.py (:class:`BackendOwnership`): the
runner declares its ``alive/backend/<id>`` token and feeds it the liveliness of
``alive/backend/*`` and ``owner/*/*``; :meth:`attach` runs the start-up liveliness get; every
tick applies the table's decision and publishes a :class:`~protocol.messages.PoseEstimate` for
each robot it may publish, flagged ``backend.<id>`` so that a bus monitor can tell who published
it.

Run one as a process (the one the test SIGKILLs)::

    python -m tests.system.ownership_probe --site lab --id b3 --robots r0,r1,r2 \
        --mode client --connect tcp/127.0.0.1:7447
"""

from __future__ import annotations

import argparse
import collections
import time
from collections.abc import Iterable, Sequence

import numpy as np

from backend_service.ownership import DEFAULT_CONFIRM_S, DEFAULT_JOIN_DELAY_S, DEFAULT_STALL_S
from backend_service.ownership_tokens import BackendOwnership
from core.runtime import Outgoing, ServiceNode, Subscription, service_main
from core.session import add_session_arguments
from protocol import keys
from protocol.messages import PoseEstimate

#: the flag that names the publishing backend on each estimate
FLAG_PREFIX = "backend."


class OwnershipProbe(ServiceNode):
    """Publishes a fixed pose of every robot it may publish, every tick."""

    service = "backend"

    def __init__(self, site: str, instance_id: str, robots: Sequence[str], *,
                 tick_period_s: float = 0.02, confirm_s: float = DEFAULT_CONFIRM_S,
                 join_delay_s: float = DEFAULT_JOIN_DELAY_S,
                 stall_s: float = DEFAULT_STALL_S) -> None:
        super().__init__(site, instance_id)
        self.tick_period_s = tick_period_s
        self.ownership = BackendOwnership(site, instance_id, robots, started_ns=time.time_ns(),
                                          confirm_s=confirm_s, join_delay_s=join_delay_s,
                                          stall_s=stall_s)
        self.table = self.ownership.table
        self._seq: collections.Counter[str] = collections.Counter()

    def subscriptions(self) -> Sequence[Subscription]:
        return self.ownership.subscriptions()

    def attach(self, session: object) -> None:
        self.ownership.attach(session, self.clock)

    def alive(self, key: str, present: bool) -> None:
        self.ownership.alive(key, present, self.clock())

    def tick(self, now_ns: int) -> Iterable[Outgoing]:
        self.ownership.tick(now_ns)
        out = []
        for robot in self.table.robots:
            if self.ownership.may_publish(robot, now_ns):
                self._seq[robot] += 1
                est = PoseEstimate(robot_id=robot, stamp_ns=now_ns, seq=self._seq[robot],
                                   x=1.0, y=2.0, theta=0.0, covariance=np.eye(3) * 1e-4,
                                   source="fused", flags=(FLAG_PREFIX + self.instance_id,))
                out.append(Outgoing(keys.pose_key(self.site, robot), est))
        return out

    def state(self) -> tuple[str, str]:
        return "ok", self.ownership.detail(self.clock())

    def counters(self) -> dict[str, int]:
        return {**self.stats.snapshot_counters(), **self.ownership.counters()}

    def close(self) -> None:
        self.ownership.close()


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="ownership_probe", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--site", required=True)
    parser.add_argument("--id", required=True)
    parser.add_argument("--robots", required=True, help="comma-separated robot ids")
    parser.add_argument("--confirm-s", type=float, default=DEFAULT_CONFIRM_S)
    parser.add_argument("--join-delay-s", type=float, default=DEFAULT_JOIN_DELAY_S)
    parser.add_argument("--stall-s", type=float, default=DEFAULT_STALL_S)
    add_session_arguments(parser)
    return parser


def build_node(args: argparse.Namespace) -> OwnershipProbe:
    return OwnershipProbe(args.site, args.id, args.robots.split(","), confirm_s=args.confirm_s,
                          join_delay_s=args.join_delay_s, stall_s=args.stall_s)


def main(argv: Sequence[str]) -> int:
    return service_main("ownership_probe", argv, build_parser, build_node)


if __name__ == "__main__":
    import sys

    sys.exit(main(sys.argv[1:]))
