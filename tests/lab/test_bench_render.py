"""``smartedge bench render`` runs and prints every configuration, the stage breakdown and the
GL floors (a smoke test at a tiny size: timings are the command's business, not the tests')."""

from __future__ import annotations

import pytest

pytest.importorskip("moderngl")

from lab.bench import render


def test_the_bench_prints_configurations_stages_and_floors(capsys) -> None:
    assert render.main(["--seconds", "0.05", "--rounds", "1", "--batch", "2", "--workers", "2",
                        "--tiles", "2", "--sizes", "96x64"]) == 0
    out = capsys.readouterr().out
    for mode in ("site 96x64", "randomized 96x64"):
        assert mode in out
    assert out.count("one view at a time (previous)") == 2
    assert out.count("pool, 2 workers") == 2 and out.count("cpu-ms/image") == 6
    assert out.count("stages, ms/image") == 2 and "augment" in out and "remap" in out
    assert out.count("GL floor, every draw") == 2 and out.count("tiled in one framebuffer") == 2
    assert out.count("GL floor as rendered") == 1  # site views keep their static render
