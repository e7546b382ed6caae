"""Areas of a site: which cameras a backend serves, and which area a robot is in.

A facility too large for one backend process is split into **areas** (site file section
``areas:``), each a set of cameras and optionally a floor polygon::

    areas:
      west:
        cameras: [cam000, cam001, cam002]
        polygon_m: [[-6, -6], [18, -6], [18, 6], [-6, 6]]   # world x, y (m)
        backends: [b0]          # optional: backends that serve it without --area
      east:
        cameras: [cam002, cam003]   # a camera on the border may belong to two areas
        polygon_m: [[18, -6], [42, -6], [42, 6], [18, 6]]

``smartedge backend --area west`` (or a backend whose ``--id`` an area lists under
``backends``) subscribes to the detections of its areas' cameras only, one subscription per
camera key, so the per-camera work (decode, association, sync) is only its areas'; it
announces the areas it serves with a liveliness token per area
(``smartedge/<site>/area/<area>/<id>``, :func:`protocol.keys.area_key`). A backend without
an area serves every camera (and counts as serving every area).

**The area of a robot** (:class:`AreaMap.area_of`): the area whose polygon holds its position;
while it is inside its current area grown by :data:`HYSTERESIS_M` it stays there (a robot on a
border does not flap between two areas). An area without a polygon holds the floor closest to
its cameras: a position outside every polygon goes to the area(s) of the nearest camera (in x,
y). The position is the robot's newest pose on the bus (its owner's fused pose, else its own
localization), which every backend receives alike, so the backends agree on the area up to the
bus's delay; where they briefly disagree the owner tokens still keep one publisher
(backend_service/ownership.py).

Pure numpy, transport-free. :func:`parse_areas` validates the section and raises
:class:`~protocol.errors.SiteConfigError` naming the file and the dotted key.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Iterable, Mapping, Sequence
from typing import Any, Final

import numpy as np

from core.config_file import join_key
from core.site import Site

#: a robot stays in its current area while it is inside the area's polygon grown by this (m)
HYSTERESIS_M: Final = 0.5
_AREA_KEYS: Final = {"cameras", "polygon_m", "backends"}


@dataclasses.dataclass(frozen=True, eq=False)
class Area:
    """One area of the site (site file ``areas.<name>``): ``cameras``, the ids of the cameras
    whose detections its backends receive (at least one; a camera may be in two areas);
    ``polygon_m``, optional floor polygon, a list of at least three ``[x, y]`` world points in
    metres (default: the floor nearest to the area's cameras); ``backends``, optional backend
    instance ids that serve this area when started without ``--area``."""

    name: str
    cameras: tuple[str, ...]
    polygon_m: np.ndarray | None = None  # (K, 2) world x, y
    backends: tuple[str, ...] = ()


def parse_areas(site: Site) -> dict[str, Area]:
    """The site's ``areas`` section, validated (empty when the file has none)."""
    section = site.section("areas")
    ctx = site.section_reader()
    out: dict[str, Area] = {}
    for name, value in section.items():
        key = join_key("areas", str(name))
        area_name = ctx.ident(key, name)
        node = ctx.mapping(key, value)
        ctx.no_unknown(key, node, set(_AREA_KEYS))
        ckey = join_key(key, "cameras")
        cams = ctx.require(key, node, "cameras")
        if not isinstance(cams, list) or not cams:
            raise ctx.fail(ckey, "expected a non-empty list of camera ids")
        cameras: list[str] = []
        for i, cam in enumerate(cams):
            ik = f"{ckey}[{i}]"
            cam_id = ctx.ident(ik, cam)
            if cam_id not in site.cameras:
                raise ctx.fail(ik, f"no camera {cam_id!r} in the site (cameras: "
                               f"{_listing(site.cameras)})")
            if cam_id in cameras:
                raise ctx.fail(ik, f"camera {cam_id!r} is listed twice")
            cameras.append(cam_id)
        polygon = None
        if node.get("polygon_m") is not None:
            pkey = join_key(key, "polygon_m")
            try:
                polygon = np.asarray(node["polygon_m"], dtype=np.float64)
            except (TypeError, ValueError):
                raise ctx.fail(pkey, "expected a list of [x, y] points") from None
            if polygon.ndim != 2 or polygon.shape[1] != 2:
                raise ctx.fail(pkey, f"expected a list of [x, y] points, got shape "
                               f"{polygon.shape}")
            if polygon.shape[0] < 3:
                raise ctx.fail(pkey, f"expected at least 3 points [x, y], got "
                               f"{polygon.shape[0]}")
            if not np.all(np.isfinite(polygon)):
                raise ctx.fail(pkey, "points must be finite")
            if abs(_signed_area(polygon)) < 1e-6:
                raise ctx.fail(pkey, "the polygon encloses no area")
            polygon.setflags(write=False)
        backends: list[str] = []
        if node.get("backends") is not None:
            bkey = join_key(key, "backends")
            if not isinstance(node["backends"], list):
                raise ctx.fail(bkey, "expected a list of backend instance ids")
            backends = [ctx.ident(f"{bkey}[{i}]", b) for i, b in enumerate(node["backends"])]
        out[area_name] = Area(area_name, tuple(cameras), polygon, tuple(backends))
    return out


def backend_areas(site: Site, requested: Sequence[str], instance_id: str) -> tuple[str, ...]:
    """The areas a backend serves: ``requested`` (``--area``, each name checked against the
    site; ``SiteConfigError`` naming the site file and ``areas`` when unknown), else the areas
    whose ``backends`` list ``instance_id``; ``()``: every camera, no area."""
    areas = parse_areas(site)
    ctx = site.section_reader()
    chosen: list[str] = []
    for name in requested:
        if name not in areas:
            raise ctx.fail(join_key("areas", name), f"--area {name!r}: no such area in the "
                           f"site (areas: {_listing(areas)})")
        if name not in chosen:
            chosen.append(name)
    if not chosen:
        chosen = [a.name for a in areas.values() if instance_id in a.backends]
    return tuple(chosen)


def _listing(ids: Iterable[str], limit: int = 12) -> str:
    ids = sorted(ids)
    shown = ", ".join(ids[:limit]) + (f", ... ({len(ids)} in all)" if len(ids) > limit else "")
    return shown or "-"


def _signed_area(poly: np.ndarray) -> float:
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(np.roll(x, -1), y))


def inside_polygon(poly: np.ndarray, x: float, y: float) -> bool:
    """Whether (x, y) lies inside ``poly`` (even-odd rule; a point on an edge may go either
    way)."""
    inside = False
    n = len(poly)
    for i in range(n):
        x1, y1 = poly[i]
        x2, y2 = poly[(i + 1) % n]
        if (y1 > y) != (y2 > y):
            xc = x1 + (y - y1) * (x2 - x1) / (y2 - y1)
            if x < xc:
                inside = not inside
    return inside


def distance_to_polygon(poly: np.ndarray, x: float, y: float) -> float:
    """Distance (m) from (x, y) to ``poly``: 0 inside, else to the nearest edge."""
    if inside_polygon(poly, x, y):
        return 0.0
    p = np.array([x, y])
    a = poly
    b = np.roll(poly, -1, axis=0)
    ab = b - a
    t = np.clip(np.einsum("ij,ij->i", p - a, ab) / np.maximum(np.einsum("ij,ij->i", ab, ab),
                                                             1e-12), 0.0, 1.0)
    closest = a + t[:, None] * ab
    return float(np.min(np.linalg.norm(closest - p, axis=1)))


class AreaMap:
    """The areas of a site and the area of a position (see the module doc)."""

    def __init__(self, site: Site, areas: Mapping[str, Area] | None = None,
                 hysteresis_m: float = HYSTERESIS_M) -> None:
        self.areas: dict[str, Area] = dict(parse_areas(site) if areas is None else areas)
        self.hysteresis_m = float(hysteresis_m)
        #: camera -> the areas it belongs to
        self.camera_areas: dict[str, tuple[str, ...]] = {}
        for area in self.areas.values():
            for cam in area.cameras:
                self.camera_areas[cam] = (*self.camera_areas.get(cam, ()), area.name)
        cams = sorted(self.camera_areas)
        self._cam_ids = cams
        self._cam_xy = (np.array([site.cameras[c].position_world[:2] for c in cams], float)
                        if cams else np.zeros((0, 2)))

    def __bool__(self) -> bool:
        return bool(self.areas)

    def cameras_of(self, names: Iterable[str]) -> tuple[str, ...]:
        """The cameras of the areas ``names`` (each once, sorted)."""
        return tuple(sorted({c for n in names for c in self.areas[n].cameras}))

    def area_of(self, x: float, y: float, current: str | None = None) -> str | None:
        """The area of a robot at (x, y) m that was in ``current`` (``None``: no area yet, or
        the site has none)."""
        if not self.areas or not (math.isfinite(x) and math.isfinite(y)):
            return current
        cur = self.areas.get(current) if current is not None else None
        if cur is not None and cur.polygon_m is not None and \
                distance_to_polygon(cur.polygon_m, x, y) <= self.hysteresis_m:
            return current
        for name in sorted(self.areas):
            poly = self.areas[name].polygon_m
            if poly is not None and inside_polygon(poly, x, y):
                return name
        if not len(self._cam_ids):
            return current
        d = np.hypot(self._cam_xy[:, 0] - x, self._cam_xy[:, 1] - y)
        k = int(np.argmin(d))
        # the nearest camera's areas, and (hysteresis) the current one while one of its
        # cameras is within HYSTERESIS_M of the nearest distance
        candidates = [a for a in self.camera_areas[self._cam_ids[k]]
                      if self.areas[a].polygon_m is None]
        if cur is not None and cur.polygon_m is None:
            near = [i for i, c in enumerate(self._cam_ids)
                    if current in self.camera_areas[c] and d[i] <= d[k] + self.hysteresis_m]
            if near:
                return current
        if candidates:
            return sorted(candidates)[0]
        # the nearest camera's areas all have polygons the position is outside of: the
        # nearest polygon
        return min(sorted(self.camera_areas[self._cam_ids[k]]),
                   key=lambda a: distance_to_polygon(self.areas[a].polygon_m, x, y))

    def describe(self) -> str:
        return "; ".join(f"{a.name}: {len(a.cameras)} cameras"
                         + (" + polygon" if a.polygon_m is not None else "")
                         for a in self.areas.values())


def area_section_doc() -> Mapping[str, Any]:
    """The keys of one ``areas.<name>`` entry with their meaning (for the configuration
    reference)."""
    return {
        "cameras": "ids of the area's cameras (required; a camera may be in two areas)",
        "polygon_m": "floor polygon, [[x, y], ...] world metres, at least 3 points "
                     "(default: the floor nearest to the area's cameras)",
        "backends": "backend instance ids that serve the area without --area",
    }
