"""Scene sampling, held-out splits, procedural probes and textures (no rendering)."""

import math

import numpy as np
import pytest
import torch

from relight_core import lighting
from relight_core.data import probes
from relight_core.data.meshes import MESHES, PRIMITIVES, build_mesh
from relight_core.data.scenes import PLACEMENT_RADIUS, object_pose, sample_scene
from relight_core.data.textures import TEXTURE_KINDS, TextureSpec, make_texture


def test_scene_is_deterministic_from_seed():
    assert sample_scene(4, "train", 17, 9) == sample_scene(4, "train", 17, 9)
    assert sample_scene(4, "train", 17, 9) != sample_scene(5, "train", 17, 9)


def test_test_split_never_uses_train_probes_meshes_or_textures():
    used = {split: {"probes": set(), "meshes": set(), "textures": set()} for split in ("train", "test")}
    for split in used:
        for index in range(60):
            spec = sample_scene(0, split, index, 9)
            used[split]["probes"] |= {p.source for p in spec.probes}
            used[split]["meshes"] |= {o.shape for o in spec.objects if o.shape not in PRIMITIVES}
            materials = [spec.ground] + [o.material for o in spec.objects]
            used[split]["textures"] |= {m.texture.kind for m in materials if m.texture is not None}
    for kind in ("probes", "meshes", "textures"):
        assert used["train"][kind] and used["test"][kind]
        assert not used["train"][kind] & used["test"][kind], kind
    assert used["test"]["probes"] == {f"file:{n}" for n in probes.TEST_PROBES}


def test_objects_never_overlap_over_the_whole_clip():
    for index in range(30):
        spec = sample_scene(1, "train", index, 9)
        assert 1 <= len(spec.objects) <= 6
        for frame in (0, 4, 8):
            poses = [np.array(object_pose(spec, o, frame)[:2]) for o in spec.objects]
            for i, a in enumerate(spec.objects):
                assert np.linalg.norm(poses[i]) <= PLACEMENT_RADIUS + 0.5
                for j in range(i):
                    gap = np.linalg.norm(poses[i] - poses[j]) - a.footprint - spec.objects[j].footprint
                    assert gap > 0, (index, frame, a.shape, spec.objects[j].shape)


def test_every_catalogue_mesh_builds_offline_and_stands_on_the_ground():
    for name in MESHES["train"] + MESHES["test"] + ("cylinder",):
        mesh = build_mesh(name, seed=3)
        assert mesh.vertices[:, 1].min() == pytest.approx(0.0, abs=1e-5)
        assert np.abs(mesh.vertices).max() <= 2.0 + 1e-4
        assert len(mesh.faces) > 10 and mesh.faces.max() < len(mesh.vertices)
        np.testing.assert_allclose(np.linalg.norm(mesh.normals, axis=1), 1.0, atol=1e-3)


def test_sun_sky_puts_the_sun_where_asked_and_its_ground_is_darker_than_the_sky():
    probe = probes.sun_sky(64, 128, elevation=30.0, azimuth=-60.0, turbidity=3.0)
    i, j = np.unravel_index(np.argmax(probe.sum(-1)), probe.shape[:2])
    peak = lighting.texel_directions(64, 128)[i, j].numpy()
    sun = probes.sun_direction(30.0, -60.0)
    assert math.degrees(math.acos(np.clip(peak @ sun, -1, 1))) < 4.0
    assert probe[48:].mean() < probe[:16].mean()  # ground (bottom rows) darker than the sky


def test_exposure_normalisation_sets_white_patch_radiance():
    probe = probes.procedural_probe("studio", np.random.default_rng(0), 32, 64)
    scaled = probes.normalise_exposure(probe, 0.6)
    assert probes.white_patch_radiance(scaled) == pytest.approx(0.6, rel=1e-4)
    # A uniform probe of radiance L lights a white patch to radiance L.
    assert probes.white_patch_radiance(np.ones((64, 128, 3), np.float32)) == pytest.approx(1.0, rel=0.01)


def test_bundled_probes_load_and_have_the_documented_sizes():
    for name in probes.POLYHAVEN:
        assert lighting.load_probe(probes.ENVMAP_DIR / f"{name}.exr").shape == (512, 1024, 3)
    for name in probes.BUNDLED_PROCEDURAL:
        stored = lighting.load_probe(probes.ENVMAP_DIR / f"{name}.exr")
        assert stored.shape == (256, 512, 3)
        # The file is what the generator makes (up to half-float rounding).
        torch.testing.assert_close(stored, torch.from_numpy(probes.bundled_procedural(name)).clamp(max=65504),
                                   rtol=2e-3, atol=1e-3)


@pytest.mark.parametrize("kind", TEXTURE_KINDS["train"] + TEXTURE_KINDS["test"])
def test_textures_are_two_colour_and_tileable(kind):
    spec = TextureSpec(kind, (0.9, 0.1, 0.1), (0.1, 0.1, 0.9), frequency=4, angle=0.3, seed=1)
    tex = make_texture(spec, 64)
    assert tex.shape == (64, 64, 3) and tex.min() >= 0.1 - 1e-6 and tex.max() <= 0.9 + 1e-6
    assert tex[..., 0].std() > 0.05
    # Opposite edges continue each other: the step across the seam is no bigger than the largest
    # step between neighbouring columns inside the texture.
    inner = np.abs(np.diff(tex, axis=1)).mean(axis=(0, 2)).max()
    assert np.abs(tex[:, 0] - tex[:, -1]).mean() <= inner + 1e-3


def test_closed_meshes_wind_outwards_so_their_fronts_face_the_camera():
    for name in ("letter_train", "letter_test", "dodecahedron", "knot", "nut"):
        for seed in range(4):
            mesh = build_mesh(name, seed)
            corners = mesh.vertices[mesh.faces]
            volume = np.einsum("ij,ij->", corners[:, 0], np.cross(corners[:, 1], corners[:, 2])) / 6
            assert volume > 0, (name, seed)
            face_normals = np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0])
            assert np.mean(np.einsum("ij,ij->i", face_normals, mesh.normals[mesh.faces].mean(1)) > 0) > 0.99


def test_the_extended_library_lights_train_scenes_with_the_extra_hdris_and_changes_nothing_else():
    # classic is what every dataset of a seed was drawn from before libraries existed (these are seed 0's draws)
    assert [p.source for p in sample_scene(0, "train", 0, 1).probes] == ["file:studio", "procedural:night"]
    assert sample_scene(0, "train", 5, 9) == sample_scene(0, "train", 5, 9, "classic")
    used = {library: set() for library in probes.PROBE_LIBRARIES}
    for library in used:
        for index in range(120):
            used[library] |= {p.source for p in sample_scene(2, "train", index, 1, library).probes}
    extra = {f"file:extra/{n}" for n in probes.EXTRA_PROBES}
    assert extra <= used["extended"] and not extra & used["classic"]
    assert not {f"file:{n}" for n in probes.TEST_PROBES} & used["extended"]
    # The held-out split is the same scenes in both, and the extra night is drawn as dark as the bundled one.
    assert all(sample_scene(0, "test", i, 1, "extended") == sample_scene(0, "test", i, 1) for i in range(20))
    nights = [p for i in range(200) for p in sample_scene(3, "train", i, 1, "extended").probes
              if p.source == "file:extra/night"]
    assert nights and all(0.15 <= p.exposure <= 0.4 for p in nights)
    with pytest.raises(ValueError, match="probe library"):
        sample_scene(0, "train", 0, 1, "everything")


def test_the_extra_hdris_load_and_none_is_a_held_out_probe_turned():
    def coarse(name):
        probe = lighting.load_probe(probes.ENVMAP_DIR / f"{name}.exr")
        assert probe.shape[1] == 2 * probe.shape[0] and probe.shape[2] == 3
        assert torch.isfinite(probe).all() and (probe >= 0).all()
        small = torch.nn.functional.adaptive_avg_pool2d(probe.permute(2, 0, 1)[None], (16, 32))[0]
        return torch.log1p(small).numpy()

    held_out = [coarse(n) for n in probes.TEST_PROBES]
    for name in probes.EXTRA_PROBES:
        extra = coarse(f"extra/{name}")
        assert probes.white_patch_radiance(probes.load_choice(
            probes.ProbeChoice(f"file:extra/{name}", 0, 0.0, 0.7))) == pytest.approx(0.7, rel=1e-3)
        for other in held_out:  # the best correlation over the 32 yaws of the coarse grid
            best = max(np.corrcoef(np.roll(extra, k, axis=2).ravel(), other.ravel())[0, 1] for k in range(32))
            assert best < 0.75, name
