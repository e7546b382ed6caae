"""``smartedge mapper``: the semantic mapping service.

:class:`~mapper.mapping.SemanticMapping` on the wire: semantic clouds of the static edge sensors
(``.../edge/<camera>/cloud``) and of the robots (``.../robot/<robot>/cloud``) and the backend's
fused poses (``.../robot/<robot>/pose``, to place the robots' clouds) in; the map's semantic
voxels on ``.../map/<id>/voxels`` every ``publish_period_s`` out, and in the status the map's
size and each robot's latest ICP alignment offset (``smartedge status`` shows it). The node
(:class:`MapperNode`) is transport-free; :func:`main` runs it on Zenoh.

A service of its own, next to the backend: ICP on a robot cloud takes tens of milliseconds, and
a pose estimate must never wait for it; the map can be restarted, or left out, without touching
localization. The map is kept in ``snapshot_path`` (site file, ``map:`` section): loaded at
start, written every ``snapshot_period_s`` and when the service stops. A snapshot that cannot be
read is moved aside (``<name>.unreadable-<time>``, logged) and the map starts from the prior.
Snapshot and prior model files are :mod:`mapper.map_io`'s.
"""

from __future__ import annotations

import argparse
import dataclasses
import logging
import os
import time
from collections.abc import Iterable, Sequence
from pathlib import Path

from core.runtime import Outgoing, ServiceNode, Subscription, service_main
from core.session import add_session_arguments
from core.site import Site, load_site
from mapper.map_io import load_map_npz, read_ply_points, save_map_npz
from mapper.mapping import MappingConfig, SemanticMapping
from mapper.semantic_map import MapError
from protocol import keys
from protocol.errors import UsageError
from protocol.messages import Message, PoseEstimate, SemanticCloud

log = logging.getLogger(__name__)


def site_relative(site: Site, path: str) -> Path:
    """``path`` as written in the site file: absolute, or relative to the site file's folder."""
    p = Path(path).expanduser()
    if p.is_absolute() or site.source_path.startswith("<"):
        return p
    return Path(site.source_path).resolve().parent / p


def load_or_start_map(site: Site, config: MappingConfig, snapshot: Path | None
                      ) -> tuple[SemanticMapping, str]:
    """The mapping with the saved map from ``snapshot`` when it exists and matches the site's
    map configuration, else from the prior model (or empty). Returns it and how it started."""
    if snapshot is not None and snapshot.exists():
        try:
            saved = load_map_npz(snapshot)
            if saved.config != config.map:
                raise MapError(f"{snapshot}: saved with another map configuration "
                               f"({saved.config}), the site file says {config.map}")
            return (SemanticMapping(site, config, initial_map=saved),
                    f"snapshot {snapshot.name} ({len(saved)} voxels)")
        except MapError as exc:
            stamp = time.strftime("%Y%m%d-%H%M%S")
            aside = snapshot.with_name(f"{snapshot.name}.unreadable-{stamp}")
            os.replace(snapshot, aside)
            log.error("map snapshot not used, moved to %s: %s", aside.name, exc)
    if config.prior_model:
        prior = site_relative(site, config.prior_model)
        points, normals = read_ply_points(prior)
        mapping = SemanticMapping(site, config, prior_points_world=points,
                                  prior_normals_world=normals)
        return mapping, f"prior model {prior.name} ({len(mapping.map)} voxels)"
    return SemanticMapping(site, config), "empty (no prior model)"


class MapperNode(ServiceNode):
    """The mapping service as a transport-free node."""

    service = "mapper"

    def __init__(self, site: Site, instance_id: str = "main", *,
                 mapping: SemanticMapping | None = None, snapshot_path: Path | None = None,
                 started_from: str = "", tick_period_s: float = 0.05) -> None:
        super().__init__(site.name, instance_id)
        self.site_model = site
        self.mapping = mapping if mapping is not None else SemanticMapping(site)
        self.config = self.mapping.config
        self.snapshot_path = snapshot_path
        self.started_from = started_from
        self.tick_period_s = tick_period_s
        self._seq = 0
        self._last_publish_s = time.monotonic()
        self._last_snapshot_s = time.monotonic()
        self._dirty = False
        self._clock_ns = 0

    def subscriptions(self) -> Sequence[Subscription]:
        s = self.site
        return [
            Subscription(keys.edge_cloud_key(s, "*"), SemanticCloud, capacity=32),
            Subscription(keys.robot_cloud_key(s, "*"), SemanticCloud, capacity=16),
            Subscription(keys.pose_key(s, "*"), PoseEstimate, capacity=4096, drop_oldest=False),
        ]

    def handle(self, key: str, message: Message, recv_ns: int) -> Iterable[Outgoing]:
        self._clock_ns = max(self._clock_ns, recv_ns)
        parsed = keys.parse_key(key)
        if isinstance(message, PoseEstimate):
            self.mapping.on_pose(message)
            return ()
        if isinstance(message, SemanticCloud):
            self.stats.event(f"clouds.{parsed.scope}")
            outcome = self.mapping.on_cloud(message, parsed.scope, parsed.source_id, recv_ns)
            self.stats.latency(f"fuse_{parsed.scope}", outcome.fuse_s)
            self._dirty |= outcome.accepted
        return ()

    def tick(self, now_ns: int) -> Iterable[Outgoing]:
        self._clock_ns = max(self._clock_ns, now_ns)
        now_s = time.monotonic()
        out: list[Outgoing] = []
        period = self.config.publish_period_s
        if period > 0 and now_s - self._last_publish_s >= period:
            self._last_publish_s = now_s
            msg = self.mapping.voxels_message(self._clock_ns, self._seq, self.instance_id)
            if msg is not None:
                self._seq += 1
                out.append(Outgoing(keys.map_voxels_key(self.site, self.instance_id), msg,
                                    reliable=False))
        if (self.snapshot_path is not None and self._dirty
                and now_s - self._last_snapshot_s >= self.config.snapshot_period_s):
            self._last_snapshot_s = now_s
            self.save_snapshot()
        return out

    def save_snapshot(self) -> bool:
        """Write the map to ``snapshot_path`` (atomically); a failure is logged and counted."""
        if self.snapshot_path is None:
            return False
        try:
            self.snapshot_path.parent.mkdir(parents=True, exist_ok=True)
            save_map_npz(self.mapping.map, self.snapshot_path)
        except OSError as exc:
            self.stats.count("snapshot_failed")
            log.error("map snapshot %s not written: %s", self.snapshot_path, exc)
            return False
        self.stats.count("snapshots")
        self._dirty = False
        return True

    def close(self) -> None:
        if self._dirty:
            self.save_snapshot()

    def state(self) -> tuple[str, str]:
        m = self.mapping.map
        detail = (f"map: {len(m)} voxels, {int(m.has_semantics().sum())} with semantics "
                  f"(started from {self.started_from or 'empty'})")
        align = self.mapping.alignment_summary()
        return "ok", f"{detail}; {align}" if align else detail

    def counters(self) -> dict[str, int]:
        out = self.stats.snapshot_counters()
        out.update(self.mapping.counter_snapshot())
        return out


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="smartedge mapper", description=__doc__,
                                     formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("--site", required=True, help="site file (its map: section)")
    parser.add_argument("--id", default="main", help="instance id (default: main)")
    parser.add_argument("--snapshot", default=None, metavar="FILE.npz",
                        help="where the map is kept (default: the site file's "
                        "map.snapshot_path; an empty string: not kept)")
    parser.add_argument("--prior-model", default=None, metavar="FILE.ply",
                        help="prior geometric model of the empty room (default: the site "
                        "file's map.prior_model)")
    add_session_arguments(parser)
    return parser


def build_node(args: argparse.Namespace) -> MapperNode:
    site = load_site(args.site)
    config = MappingConfig.from_site(site)
    if args.prior_model is not None:
        config = dataclasses.replace(config, prior_model=str(Path(args.prior_model).resolve()))
    # paths on the command line are relative to the working directory, those in the site file
    # to the site file's folder
    if args.snapshot is not None:
        snapshot = Path(args.snapshot).expanduser().resolve() if args.snapshot else None
    else:
        snapshot = (site_relative(site, config.snapshot_path) if config.snapshot_path
                    else None)
    if snapshot is not None and snapshot.suffix != ".npz":
        raise UsageError(f"map snapshot {snapshot}: expected a .npz file")
    try:
        mapping, started = load_or_start_map(site, config, snapshot)
    except MapError as exc:
        raise UsageError(f"map: {exc}") from exc
    log.info("mapper: map started from %s", started)
    return MapperNode(site, args.id, mapping=mapping, snapshot_path=snapshot,
                      started_from=started)


def main(argv: Sequence[str]) -> int:
    """``smartedge mapper`` with ``argv`` (the arguments after the command): the node on Zenoh
    until stopped; returns the exit status."""
    return service_main("mapper", argv, build_parser, build_node)
