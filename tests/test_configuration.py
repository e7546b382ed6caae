"""Package-owned site-file sections: parsed by their package, errors name file and key, and the
configuration reference page is the one the code generates."""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

pytest.importorskip("gtsam")

from backend_service.fusion import fusion_config_from_site
from backend_service.pipeline_config import PipelineConfig
from core.site import load_site
from protocol.errors import SiteConfigError, SmartedgeError
from smartedge.config_reference import field_names, render

REPO = Path(__file__).resolve().parents[1]
EXAMPLE = REPO / "deploy" / "site.example.yaml"


def _site_with(tmp_path: Path, **sections: object):
    doc = yaml.safe_load(EXAMPLE.read_text())
    doc.update(sections)
    path = tmp_path / "site.yaml"
    path.write_text(yaml.safe_dump(doc))
    return load_site(path)


def test_reference_page_is_generated_from_the_code() -> None:
    assert (REPO / "docs" / "configuration.md").read_text() == render(), (
        "docs/configuration.md is stale: run smartedge site reference > docs/configuration.md")


def test_every_documented_key_is_accepted(tmp_path: Path) -> None:
    keys = field_names()
    assert {"prior", "robust_loss", "method"} <= keys["pose"]
    assert {"window_s", "robust_kernel"} <= keys["fusion"]
    assert {"count", "max_jump_m"} <= keys["multi_frame"]
    site = _site_with(tmp_path, pose={"robust_loss": "cauchy", "prior": "localization",
                                      "fuse_while_moving": False},
                      multi_frame={"count": 7, "max_jump_m": 0.2},
                      fusion={"window_s": 100.0, "robust_kernel": "cauchy"})
    config = PipelineConfig.from_site(site)
    assert config.solver.robust_loss == "cauchy" and config.prior == "localization"
    assert not config.fuse_while_moving
    assert config.multi_frame.count == 7 and config.multi_frame.max_jump_m == 0.2
    fusion = fusion_config_from_site(site)
    assert fusion.window_s == 100.0 and fusion.robust_kernel == "cauchy"


@pytest.mark.parametrize(
    ("sections", "key"),
    [
        ({"pose": {"prior": "gps"}}, "pose"),
        ({"pose": {"robust_los": "huber"}}, "pose.robust_los"),
        ({"pose": {"fuse_while_moving": 1}}, "pose.fuse_while_moving"),
        ({"multi_frame": {"count": 0}}, "multi_frame.count"),
        ({"fusion": {"window_s": -1}}, "fusion.window_s"),
        ({"fusion": {"robust_kernel": "tukey"}}, "fusion"),
    ],
)
def test_bad_values_name_file_and_key(tmp_path: Path, sections: dict, key: str) -> None:
    site = _site_with(tmp_path, **sections)
    with pytest.raises(SiteConfigError) as err:
        PipelineConfig.from_site(site)
        fusion_config_from_site(site)
    assert str(tmp_path / "site.yaml") in str(err.value)
    assert f": {key}" in str(err.value)
    assert isinstance(err.value, SmartedgeError)


def test_unknown_section_is_an_error(tmp_path: Path) -> None:
    with pytest.raises(SiteConfigError, match="fuson"):
        _site_with(tmp_path, fuson={"window_s": 1.0})


def test_bridge_section(tmp_path: Path) -> None:
    from robot_bridge.bridge import BridgeConfig

    site = _site_with(tmp_path, bridge={"backend_timeout_s": 7.5})
    config = BridgeConfig.from_site(site, "hsr")
    assert config.backend_timeout_s == 7.5 and config.world_frame == site.world_frame
    assert config.thresholds == site.thresholds
    bad = _site_with(tmp_path, bridge={"robot_id": "x"})
    with pytest.raises(SiteConfigError, match=r"bridge\.robot_id: unknown key"):
        BridgeConfig.from_site(bad, "hsr")
