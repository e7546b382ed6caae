"""Batched rendering and the worker pool give exactly the images and labels of one view at a
time: ``Renderer.render_many``, ``SampleGenerator.samples``, ``SamplePool`` and the batched
helpers behind them (closed-part detection of many meshes, one framebuffer for every lens).
"""

from __future__ import annotations

import dataclasses
import json

import cv2
import numpy as np
import pytest

pytest.importorskip("moderngl")

from simulation.dataset import SampleGenerator, SamplePool, sample_summary
from simulation.image_effects import augment
from simulation.labels import instance_bbox, keypoint_labels
from simulation.mesh import (
    Mesh,
    Scene,
    SceneObject,
    closed_outward_faces,
    closed_outward_faces_many,
)
from simulation.render_gl import Renderer, RenderOutput
from simulation.render_stages import STAGES, StageTimes
from simulation.robot_mesh import box, cylinder
from simulation.scenario import load_scenario
from simulation.scenes import ROBOT_INSTANCE, robot_keypoints_world

W, H = 200, 120


@pytest.fixture(scope="module")
def scenario():
    return load_scenario()


def assert_same_output(a: RenderOutput, b: RenderOutput) -> None:
    assert np.array_equal(a.color_rgb, b.color_rgb)
    assert np.array_equal(a.depth_m, b.depth_m)  # inf where nothing: equal
    assert np.array_equal(a.instance_id, b.instance_id)
    assert np.array_equal(a.class_id, b.class_id)


def assert_same_sample(a, b) -> None:
    assert a.index == b.index and a.mode == b.mode
    for name in ("image_rgb", "depth_m", "class_id", "instance_id", "robot_pose"):
        assert np.array_equal(getattr(a, name), getattr(b, name)), name
    # as JSON text: NaN pixels (keypoints behind the camera) compare equal there
    labels_a, labels_b = ([r.to_json() for r in s.robots] for s in (a, b))
    assert json.dumps(labels_a) == json.dumps(labels_b)


def _views(scenario, mode: str, n: int, seed: int = 2):
    gen = SampleGenerator(scenario, mode, seed=seed, width=W, height=H)
    return gen, [gen.view(i) for i in range(n)]


def test_render_many_equals_one_view_at_a_time(scenario) -> None:
    """Site and randomized views mixed (distorted lenses of different internal sizes, so the
    shared framebuffer is re-used at several sizes), against a fresh renderer per view."""
    gen_site, site = _views(scenario, "site", 4)
    gen_rand, rand = _views(scenario, "randomized", 4)
    views = [(v.scene, v.camera) for pair in zip(rand, site, strict=True) for v in pair]
    sizes = {gen_rand.renderer(W, H).lens_map(c).render_size for _, c in views}
    assert len(sizes) > 2
    batched = gen_rand.renderer(W, H).render_many(views)
    model = gen_site.model
    for (scene, camera), out, v in zip(views, batched, [x for p in zip(rand, site, strict=True)
                                                        for x in p], strict=True):
        with Renderer(W, H) as fresh:
            single = fresh.render(scene, camera)
        assert_same_output(out, single)
        kp_world = robot_keypoints_world(model, v.robot_pose)
        a, b = keypoint_labels(out, camera, kp_world), keypoint_labels(single, camera, kp_world)
        assert np.array_equal(a.visible, b.visible) and np.array_equal(a.in_image, b.in_image)
        assert np.array_equal(a.pixels_px, b.pixels_px, equal_nan=True)
        box_a, box_b = instance_bbox(out, ROBOT_INSTANCE), instance_bbox(single, ROBOT_INSTANCE)
        assert (box_a is None and box_b is None) or np.array_equal(box_a, box_b)


def test_render_many_fills_given_outputs_and_checks_them(scenario) -> None:
    gen, views = _views(scenario, "site", 2)
    renderer = gen.renderer(W, H)
    outs = [RenderOutput.empty(W, H) for _ in views]
    got = renderer.render_many([(v.scene, v.camera) for v in views], outs)
    assert all(g is o for g, o in zip(got, outs, strict=True))
    with pytest.raises(ValueError, match="outputs for"):
        renderer.render_many([(v.scene, v.camera) for v in views], outs[:1])
    assert renderer.render_many([]) == []


@pytest.mark.parametrize("mode", ["site", "randomized", "robot"])
def test_generator_batches_equal_single_samples(scenario, mode: str) -> None:
    kw = {} if mode == "robot" else {"width": W, "height": H}
    batched = SampleGenerator(scenario, mode, seed=11, **kw).samples(list(range(5)))
    single = SampleGenerator(scenario, mode, seed=11, **kw)
    for sample in batched:
        assert_same_sample(sample, single(sample.index))


def test_stage_times_cover_the_stages_and_do_not_change_the_images(scenario) -> None:
    timed = SampleGenerator(scenario, "randomized", seed=4, width=W, height=H)
    timed.times = StageTimes()
    samples = timed.samples([0, 1, 2])
    ms = timed.times.per_image_ms()
    assert timed.times.images == 3 and set(ms) == set(STAGES)
    for stage in ("scene", "lens_map", "draw", "read_back", "remap", "labels", "augment"):
        assert ms[stage] > 0.0, stage
    plain = SampleGenerator(scenario, "randomized", seed=4, width=W, height=H)
    for sample in samples:
        assert_same_sample(sample, plain(sample.index))


def test_sample_pool_gives_the_serial_samples(scenario) -> None:
    """Two worker processes with their own GL contexts, one rasterizer and one OpenCV thread
    each, chunks of 2: the same samples, in index order, as the serial generator."""
    serial = SampleGenerator(scenario, "randomized", seed=6, width=160, height=96)
    indices = [3, 0, 7, 1, 2]
    with SamplePool(serial, workers=2, chunk=2) as pool:
        pooled = list(pool.samples(indices))
        summaries = list(pool.map(sample_summary, indices))
        assert pool.cpu_seconds > 0.0
    assert [s.index for s in pooled] == indices
    for sample in pooled:
        assert_same_sample(sample, serial(sample.index))
    assert json.dumps(summaries) == json.dumps([sample_summary(serial(i)) for i in indices])


def test_sample_pool_of_site_views_matches_serial(scenario) -> None:
    serial = SampleGenerator(scenario, "site", seed=6, width=160, height=96)
    with SamplePool(serial, workers=2, chunk=3, gl_threads=None, cv_threads=None) as pool:
        pooled = list(pool.samples(range(4)))
    for sample in pooled:
        assert_same_sample(sample, serial(sample.index))


def _augment_reference(image_rgb: np.ndarray, rng: np.random.Generator) -> np.ndarray:
    """The augmentation as first written (numpy clip for the noise, strided views for the
    codec): the faster one must give the same images."""
    gain = rng.uniform(0.6, 1.4) * rng.uniform(0.85, 1.15, 3)
    bias = rng.uniform(-30, 30)
    lut = np.clip(np.arange(256)[:, None] * gain + bias, 0, 255).astype(np.uint8)
    img = cv2.LUT(image_rgb, lut.reshape(256, 1, 3))
    sat = rng.uniform(0.5, 1.5)
    gray = cv2.cvtColor(cv2.cvtColor(img, cv2.COLOR_RGB2GRAY), cv2.COLOR_GRAY2RGB)
    img = cv2.addWeighted(img, sat, gray, 1.0 - sat, 0.0)
    if rng.uniform() < 0.3:
        k = int(rng.choice([3, 5]))
        img = cv2.GaussianBlur(img, (k, k), 0)
    sigma = rng.uniform(0, 8)
    if sigma > 0.5:
        noise = np.empty(img.shape, np.int16)
        cv2.setRNGSeed(int(rng.integers(2**31)))
        cv2.randn(noise, 0, sigma)
        img = np.clip(img.astype(np.int16) + noise, 0, 255).astype(np.uint8)
    if rng.uniform() < 0.6:
        ok, buf = cv2.imencode(".jpg", img[..., ::-1], [cv2.IMWRITE_JPEG_QUALITY,
                                                         int(rng.integers(40, 96))])
        if ok:
            img = cv2.imdecode(buf, cv2.IMREAD_COLOR)[..., ::-1]
    return np.ascontiguousarray(img)


def test_augmentation_is_the_reference_augmentation() -> None:
    base = cv2.GaussianBlur(np.random.default_rng(0).integers(0, 256, (96, 160, 3), np.uint8),
                            (7, 7), 0)
    for seed in range(24):  # covers blur, noise and JPEG on and off
        a = augment(base, np.random.default_rng(seed))
        b = _augment_reference(base, np.random.default_rng(seed))
        assert a.flags.c_contiguous and np.array_equal(a, b), seed


def test_closed_faces_of_many_meshes_equal_one_mesh_at_a_time() -> None:
    unit = box((1.0, 1.0, 1.0))
    panel = Mesh(np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0.0]]),
                 np.array([[0, 1, 2], [0, 2, 3]]), np.array([0.5, 0.5, 0.5]))
    inside_out = dataclasses.replace(unit, faces=unit.faces[:, ::-1].copy())
    meshes = [unit, box((1.0, 1.0, 1.0)), panel, cylinder(0.3, 0.0, 1.0, segments=12),
              inside_out, Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.uint32), (0.1, 0.1, 0.1)),
              unit]  # two boxes at the same place: vertices of different meshes never weld
    many = closed_outward_faces_many(meshes)
    for mesh, closed in zip(meshes, many, strict=True):
        assert np.array_equal(closed, closed_outward_faces(mesh))
    assert many[0].all() and many[3].all()
    assert not many[2].any() and not many[4].any() and len(many[5]) == 0


def test_upload_ahead_and_one_framebuffer_for_all_lenses(scenario) -> None:
    _, views = _views(scenario, "randomized", 3)
    renderer = Renderer(W, H)
    meshes = [o.mesh for v in views for o in v.scene.objects]
    new = renderer.upload(meshes)
    assert new == len({id(m) for m in meshes if len(m.faces)})
    assert renderer.upload(meshes) == 0
    before = renderer.num_uploaded_meshes
    renderer.render_many([(v.scene, v.camera) for v in views])
    assert renderer.num_uploaded_meshes == before  # nothing uploaded twice
    renderer.release()


def test_gl_floor_replays_the_draws_untiled_and_tiled(scenario) -> None:
    gen, views = _views(scenario, "site", 3)
    renderer = gen.renderer(W, H)
    pairs = [(v.scene, v.camera) for v in views]
    before = renderer.render(*pairs[0])
    for tiles in (1, 4):
        seconds = renderer.gl_floor(pairs, seconds=0.05, tiles=tiles)
        assert 0.0 < seconds < 1.0
    # the floor's own framebuffer is gone; rendering is unchanged
    assert_same_output(renderer.render(*pairs[0]), before)


def test_scene_object_without_faces_is_skipped_in_batches(scenario) -> None:
    gen, (v,) = _views(scenario, "site", 1)
    empty = SceneObject(Mesh(np.zeros((0, 3)), np.zeros((0, 3), np.uint32), (0.2, 0.2, 0.2)),
                        np.eye(4), 5, 3)
    with_empty = Scene((*v.scene.objects, empty))
    a, b = gen.renderer(W, H).render_many([(with_empty, v.camera), (v.scene, v.camera)])
    assert_same_output(a, b)


def test_kept_static_render_gives_the_one_pass_image(scenario, monkeypatch) -> None:
    """Site scenes mark the site's own objects static: the renderer keeps their render (and
    its image) per camera, draws the robot and people on top and reads back and remaps only
    the image regions they can reach. Same images as drawing everything, over cache hits,
    misses, evictions, a framebuffer that grows in between, people behind or beside the
    camera, and distorted, undistorted and strongly distorted lenses."""
    import simulation.render_gl as render_gl

    _, site = _views(scenario, "site", 24)
    _, rand = _views(scenario, "randomized", 2)
    assert all(v.scene.static_objects > 0 for v in site)
    assert len({v.camera.camera_id for v in site}) < len(site)  # some renders are re-used
    kept = Renderer(W, H)
    plain = Renderer(W, H)
    regions = []
    real = kept._read_back_regions

    def spy(*args, **kwargs):
        regions.append(args[4])
        return real(*args, **kwargs)

    monkeypatch.setattr(kept, "_read_back_regions", spy)
    order = site[:12] + rand[:1] + site[12:] + rand[1:] + site[:4]
    lenses = (None, np.zeros(5), np.array([-0.3, 0.1, 0.0, 0.0, 0.0]))  # own, none, strong
    for step, v in enumerate(order):
        if step == 20:  # room for one kept render only from here on: evictions
            monkeypatch.setattr(render_gl, "STATIC_CACHE_BYTES", 1)
        lens = lenses[step % 3]
        camera = v.camera if lens is None else dataclasses.replace(v.camera, dist=lens)
        flat = dataclasses.replace(v.scene, static_objects=0)
        assert_same_output(kept.render(v.scene, camera), plain.render(flat, camera))
        assert len(kept._static) >= (v.scene.static_objects > 0)
        assert not plain._static
    # most site views were read back in regions only, and those are small
    assert len(regions) >= 16
    area = [sum((x1 - x0 + 1) * (y1 - y0 + 1) for x0, y0, x1, y1 in r) for r in regions]
    assert np.median(area) < 0.25 * W * H
    kept.release()
    plain.release()
    with pytest.raises(ValueError, match="static_objects"):
        Scene((), static_objects=1)
