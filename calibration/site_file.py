"""Writing calibrated camera poses into a site file: the one place ``smartedge calibrate
extrinsics`` and ``smartedge calibrate robot`` (and the evaluation) write ``cameras:`` poses.

The site file is re-written from its parsed content: the named cameras' ``T_cam_world`` /
``T_world_cam`` become one ``T_world_cam: {translation_m, quaternion_xyzw}``, optionally a
camera's inline intrinsics become a ``calibration_file:``, and every other key is kept as it was.
YAML comments of the original are not kept (PyYAML does not read them); the written file says so
in its header, above the caller's own header lines (report, uncertainties). Relative paths of the
original (``calibration_file``, robot models) are rebased onto the written file's folder, and
the written file is loaded back from where it lies and checked before it is handed back.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from core.config_file import ConfigReader, read_yaml_file
from core.geometry import rotation_to_quaternion
from core.site import Site, SiteConfigError, parse_site
from protocol.errors import SmartedgeError

__all__ = ["pose_node", "site_document_with_cameras", "write_site_with_cameras"]

#: what the written file says about the original's comments (last header line)
COMMENTS_NOTE = "comments of the original file are not kept by smartedge calibrate"
#: inline intrinsics keys a ``calibration_file:`` replaces
_INTRINSICS_KEYS = ("K", "intrinsics", "distortion", "resolution")


def pose_node(T_world_cam: np.ndarray) -> dict[str, list[float]]:
    """A ``T_world_cam`` (4, 4) as the site file writes it: translation (m, 1 um) and unit
    quaternion (x, y, z, w)."""
    T = np.asarray(T_world_cam, np.float64)
    q = rotation_to_quaternion(T[:3, :3])
    return {"translation_m": [round(float(v), 6) for v in T[:3, 3]],
            "quaternion_xyzw": [round(float(v), 9) for v in q]}


def _relative(path: Path, folder: Path) -> str:
    try:
        return os.path.relpath(path.resolve(), folder.resolve())
    except ValueError:  # another drive
        return str(path.resolve())


def _rebase(raw: Any, from_dir: Path, to_dir: Path) -> Any:
    """A relative path string of a file in ``from_dir`` as seen from ``to_dir``."""
    if not isinstance(raw, str) or not raw.strip() or from_dir.resolve() == to_dir.resolve():
        return raw
    p = Path(raw).expanduser()
    return raw if p.is_absolute() else _relative(from_dir / p, to_dir)


def site_document_with_cameras(site_path: str | Path, T_world_cam: Mapping[str, np.ndarray],
                               calibration_files: Mapping[str, str | Path] | None = None,
                               out_dir: str | Path | None = None) -> dict[str, Any]:
    """The parsed site file with the named cameras' poses replaced; everything else as it was.

    ``calibration_files``: camera id -> intrinsics file (``calibrate intrinsics``' camera_info
    YAML) that replaces that camera's inline intrinsics. ``out_dir``: the folder the document
    will be written to (default: the site file's): relative paths are written relative to it.
    Raises :class:`SiteConfigError` naming the file and key when the file has no camera list
    or a named camera is not in it."""
    site_dir = Path(site_path).parent
    to_dir = Path(out_dir) if out_dir is not None else site_dir
    doc = read_yaml_file(site_path, "site file", SiteConfigError)
    ctx = ConfigReader(str(site_path))
    cams = ctx.require("", ctx.mapping("", doc), "cameras")
    if not isinstance(cams, list):
        raise SiteConfigError(str(site_path), "cameras", "expected a list of cameras")
    wanted = {str(k) for k in T_world_cam} | {str(k) for k in (calibration_files or {})}
    done: set[str] = set()
    for i, entry in enumerate(cams):
        if not isinstance(entry, dict):
            raise SiteConfigError(str(site_path), f"cameras[{i}]",
                                  f"expected a mapping, got {type(entry).__name__}")
        cid = str(entry.get("id"))
        if "calibration_file" in entry:
            entry["calibration_file"] = _rebase(entry["calibration_file"], site_dir, to_dir)
        calib = (calibration_files or {}).get(cid)
        if calib is not None:
            for key in _INTRINSICS_KEYS:
                entry.pop(key, None)
            entry["calibration_file"] = _relative(Path(calib), to_dir)
            done.add(cid)
        if cid in T_world_cam:
            entry.pop("T_cam_world", None)
            entry["T_world_cam"] = pose_node(np.asarray(T_world_cam[cid], np.float64))
            done.add(cid)
    missing = sorted(wanted - done)
    if missing:
        raise SiteConfigError(str(site_path), "cameras", f"no camera with id {missing}")
    models = doc.get("robot_models")
    if isinstance(models, dict):
        for node in models.values():
            files = node.get("models") if isinstance(node, dict) else None
            if isinstance(files, dict):
                for kind in list(files):
                    files[kind] = _rebase(files[kind], site_dir, to_dir)
    return doc


def write_site_with_cameras(site_path: str | Path, out_path: str | Path,
                            T_world_cam: Mapping[str, np.ndarray], header: str = "",
                            calibration_files: Mapping[str, str | Path] | None = None) -> Site:
    """Write ``site_path`` with the named cameras' poses (and optionally intrinsics files)
    replaced to ``out_path``: ``header`` lines first as comments, then :data:`COMMENTS_NOTE`,
    then the document. The written file is loaded back from ``out_path`` and each written pose
    checked; returns it parsed. Raises :class:`SiteConfigError` for a bad site file and
    :class:`SmartedgeError` when the file does not read back as written."""
    out = Path(out_path)
    doc = site_document_with_cameras(site_path, T_world_cam, calibration_files, out.parent)
    text = yaml.safe_dump(doc, sort_keys=False, default_flow_style=None, width=100)
    lines = [f"# {line}".rstrip() for line in header.splitlines()] if header else []
    lines.append(f"# {COMMENTS_NOTE}")
    out.parent.mkdir(parents=True, exist_ok=True)
    out.write_text("\n".join(lines) + "\n" + text, encoding="utf-8")
    site = parse_site(yaml.safe_load(out.read_text(encoding="utf-8")), str(out), out.parent)
    for cid, T in T_world_cam.items():
        if not np.allclose(site.cameras[cid].T_world_cam, np.asarray(T, np.float64), atol=1e-5):
            raise SmartedgeError(f"{out}: camera {cid!r} did not read back as written")
    return site
