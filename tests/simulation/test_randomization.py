"""Domain randomization of training views and the held-out renderer variations: the held-out
settings are disjoint from training's (and the check can fail), lights and materials change the
render as they should, the camera effects and the robot's shadow change only what they
should, and held-out views are drawn from the held-out ranges."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest

from simulation.scenes import (
    HELD_OUT_DISJOINT_FIELDS,
    HELD_OUT_VARIATION,
    TEXTURE_KINDS,
    RandomizationConfig,
    RandomizationError,
    check_disjoint,
    light_rgb,
    procedural_texture,
    robot_appearances,
    robot_distance_m,
)

#: camera effects that leave the image as rendered (every random draw still happens)
NEUTRAL = dict(vignetting_probability=0.0, defocus_probability=0.0, motion_blur_probability=0.0,
               exposure_ev=(0.0, 0.0), white_balance=(1.0, 1.0), gamma=(1.0, 1.0),
               saturation=(1.0, 1.0), brightness_offset=(0.0, 0.0), noise_sigma=(0.0, 0.0),
               jpeg_probability=0.0, dirt_probability=0.0)


def test_held_out_settings_are_disjoint_from_the_training_defaults() -> None:
    check_disjoint(RandomizationConfig(), HELD_OUT_VARIATION)


@pytest.mark.parametrize("change, field", [
    (dict(ambient=(0.1, 0.6)), "ambient"),
    (dict(textures=("checker", "planks")), "textures"),
    (dict(occluder_shapes=("person", "pole")), "occluder_shapes"),
    (dict(k1_range=(-0.25, 0.08)), "k1_range"),
    (dict(light_temperature_k=(2700.0, 7000.0)), "light_temperature_k"),
    (dict(vignetting=(0.0, 0.5)), "vignetting"),
])
def test_disjointness_check_fails_on_overlapping_training_settings(change, field) -> None:
    training = dataclasses.replace(RandomizationConfig(), **change)
    with pytest.raises(RandomizationError, match=field):
        check_disjoint(training, HELD_OUT_VARIATION)


def test_undistorted_lenses_count_in_the_lens_check() -> None:
    """Training with undistorted lenses draws k1 = 0: a held-out k1 range through 0 overlaps."""
    held = dataclasses.replace(HELD_OUT_VARIATION, k1_range=(-0.02, -0.01))
    training = dataclasses.replace(RandomizationConfig(), k1_range=(-0.25, -0.05))
    with pytest.raises(RandomizationError, match="k1_range"):
        check_disjoint(training, held)
    check_disjoint(dataclasses.replace(training, no_distortion_probability=0.0), held,
                   fields=("k1_range",))
    assert set(HELD_OUT_DISJOINT_FIELDS) <= {f.name for f in dataclasses.fields(held)}


def test_bad_randomization_settings_are_refused() -> None:
    with pytest.raises(RandomizationError, match="jpeg_probability"):
        RandomizationConfig(jpeg_probability=1.5)
    with pytest.raises(RandomizationError, match="ambient"):
        RandomizationConfig(ambient=(0.6, 0.2))
    with pytest.raises(RandomizationError, match="marble"):
        RandomizationConfig(textures=("marble",))


def test_light_colours_follow_the_colour_temperature() -> None:
    warm, cold = light_rgb(3000.0), light_rgb(9000.0)
    assert warm[0] > warm[2] and cold[2] > cold[0]
    assert np.isclose(warm.mean(), 1.0) and np.isclose(cold.mean(), 1.0)
    assert light_rgb(5000.0, 0.1)[1] > light_rgb(5000.0)[1]


def test_every_texture_kind_is_a_distinct_image() -> None:
    images = [procedural_texture(np.random.default_rng(1), 64, (kind,)) for kind in TEXTURE_KINDS]
    for img in images:
        assert img.shape == (64, 64, 3) and img.dtype == np.uint8 and img.std() > 3
    assert len({img.tobytes() for img in images}) == len(images)


def test_robot_appearances_change_colours_not_geometry() -> None:
    from simulation.robot_mesh import hsr_like_mesh
    from simulation.scenario import load_scenario

    scenario = load_scenario()
    mesh = hsr_like_mesh(scenario.site.robot_model(scenario.robot_id))
    variants = robot_appearances(mesh, 3, RandomizationConfig(robot_appearances=4))
    assert len(variants) == 4 and variants[0] is mesh
    for v in variants[1:]:
        assert np.array_equal(v.vertices, mesh.vertices) and np.array_equal(v.faces, mesh.faces)
        assert not np.allclose(v.colors, mesh.colors)
        assert v.colors.min() >= 0.0 and v.colors.max() <= 1.0


# ---------------------------------------------------------------------------------- rendering

moderngl = pytest.importorskip("moderngl")


def _lit_box_image(**lighting) -> np.ndarray:
    from simulation.mesh import Scene, SceneObject
    from simulation.render_gl import Renderer
    from simulation.robot_mesh import box
    from simulation.scenes import look_at_camera

    cam = look_at_camera("c", np.array([2.0, -1.5, 1.6]), np.array([0.0, 0.0, 0.3]), 96, 64,
                         60.0)
    obj = SceneObject(box((0.8, 0.8, 0.6), color=(0.7, 0.7, 0.7)), np.eye(4), 1, 3)
    scene = Scene((obj,), light_dir_world=(0.3, -0.4, 1.0), ambient=0.3, **lighting)
    with Renderer(96, 64) as r:
        out = r.render(scene, cam)
    assert (out.instance_id == 1).sum() > 500
    return out.color_rgb[out.instance_id == 1].astype(np.float64)


def test_coloured_fill_and_specular_lights_change_the_shading() -> None:
    plain = _lit_box_image()
    assert np.allclose(plain[:, 0], plain[:, 2], atol=1)  # white light on grey: grey
    warm = _lit_box_image(light_rgb=tuple(light_rgb(3000.0)))
    assert warm[:, 0].mean() > warm[:, 2].mean() + 20
    fill = _lit_box_image(fill_dir_world=(-1.0, 1.0, 0.2), fill_rgb=(0.0, 0.0, 0.8))
    assert fill[:, 2].mean() > plain[:, 2].mean() + 5 and np.allclose(fill[:, 0], plain[:, 0],
                                                                       atol=1)
    shiny = _lit_box_image(specular=0.8, shininess=4.0)
    assert shiny.mean() > plain.mean() + 5


@pytest.fixture(scope="module")
def scenario():
    from simulation.scenario import load_scenario

    return load_scenario()


def test_camera_effects_are_deterministic_and_vignetting_darkens_the_corners() -> None:
    from simulation.image_effects import camera_effects

    grey = np.full((60, 100, 3), 160, np.uint8)
    cfg = RandomizationConfig()
    a = camera_effects(grey, np.random.default_rng(4), cfg)
    b = camera_effects(grey, np.random.default_rng(4), cfg)
    assert np.array_equal(a, b) and a.shape == grey.shape and a.dtype == np.uint8
    neutral = dataclasses.replace(cfg, **NEUTRAL)
    assert np.array_equal(camera_effects(grey, np.random.default_rng(4), neutral), grey)
    vignette = dataclasses.replace(neutral, vignetting_probability=1.0, vignetting=(0.5, 0.5))
    v = camera_effects(grey, np.random.default_rng(4), vignette).astype(float)
    assert v[25:35, 45:55].mean() > 150 and v[:5, :5].mean() < 110
    blur = dataclasses.replace(neutral, motion_blur_probability=1.0)
    checker = np.kron((np.indices((6, 10)).sum(axis=0) % 2) * 140 + 20,
                      np.ones((10, 10)))[..., None].repeat(3, axis=2).astype(np.uint8)
    for seed in range(3):  # any direction blurs a checkerboard
        blurred = camera_effects(checker, np.random.default_rng(seed), blur)
        assert np.abs(blurred.astype(int) - checker).max() > 20
        assert abs(blurred.astype(float).mean() - checker.mean()) < 2  # blur keeps the level


def test_the_robot_shadow_darkens_only_the_floor(scenario) -> None:
    from simulation.dataset import SampleGenerator
    from simulation.mesh import CLASS_ID

    base = dataclasses.replace(RandomizationConfig(), environments=2, robot_appearances=2,
                               **NEUTRAL)
    gens = [SampleGenerator(scenario, "randomized", seed=8, width=320, height=192,
                            randomization=dataclasses.replace(base, shadow_probability=p))
            for p in (1.0, 0.0)]
    darker = 0
    for index in range(4):
        with_shadow, without = (gen(index) for gen in gens)
        diff = with_shadow.image_rgb.astype(int) - without.image_rgb.astype(int)
        changed = np.any(diff != 0, axis=2)
        assert np.all(diff <= 0)  # only darker
        assert np.all(with_shadow.class_id[changed] == CLASS_ID["floor"])
        darker += int(changed.sum())
    assert darker > 200


def test_held_out_views_are_drawn_from_the_held_out_ranges(scenario) -> None:
    from simulation.dataset import SampleGenerator

    gen = SampleGenerator(scenario, "randomized", seed=3, width=320, height=192,
                          randomization=HELD_OUT_VARIATION)
    for sample in gen.samples(list(range(6))):
        k1 = float(sample.camera.dist[0])
        assert HELD_OUT_VARIATION.k1_range[0] <= k1 <= HELD_OUT_VARIATION.k1_range[1]
        assert 1.8 <= sample.camera.position_world[2] <= 3.2
        assert 1.5 - 1e-9 <= robot_distance_m(sample.camera, sample.robot_pose) <= 8.0 + 1e-9
        scene = gen.view(sample.index).scene
        assert HELD_OUT_VARIATION.ambient[0] <= scene.ambient <= HELD_OUT_VARIATION.ambient[1]


def test_arm_poses_move_only_the_arm_and_keep_it_above_the_base() -> None:
    from simulation.robot_mesh import hsr_like_mesh, hsr_like_parts
    from simulation.scenario import load_scenario
    from simulation.scenes import hsr_arm_poses

    scenario = load_scenario()
    model = scenario.site.robot_model(scenario.robot_id)
    rest = hsr_like_mesh(model)
    z_base_top = float(hsr_like_parts(model)["base"].bounds()[1][2])
    poses = hsr_arm_poses(model, 0, 5)
    assert len(poses) == 5
    for mesh in poses:
        assert mesh.vertices.shape == rest.vertices.shape
        moved = np.any(np.abs(mesh.vertices - rest.vertices) > 1e-6, axis=1)
        assert 0 < moved.sum() < 0.5 * len(moved)  # the arm, not the robot
        assert mesh.vertices[moved, 2].min() > z_base_top  # the base (keypoints) stays free
    assert len({m.vertices.tobytes() for m in poses}) == len(poses)


def test_arm_poses_reach_randomized_views_only_when_asked(scenario) -> None:
    from simulation.dataset import SampleGenerator

    def shapes(**kw) -> int:
        cfg = RandomizationConfig(environments=1, robot_appearances=4, **kw)
        gen = SampleGenerator(scenario, "randomized", seed=1, randomization=cfg)
        return len({m.vertices.tobytes() for m in gen.appearances()})

    assert shapes(robot_arm_poses=False) == 1  # colours only
    assert shapes() == 4  # arm poses are on by default
