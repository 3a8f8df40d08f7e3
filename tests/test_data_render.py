"""Mitsuba rendering: the envmap convention, shared geometry across lights, albedo = base colour;
render-data on Ray: the same files as one process, a failed scene alone, resume; SIGTERM stops it."""

import csv
import json
import math
import signal

import numpy as np
import pytest
import torch

pytest.importorskip("mitsuba")

from relight_core import lighting  # noqa: E402
from relight_core.colour import linear_to_srgb  # noqa: E402
from relight_core.data.probes import ProbeChoice  # noqa: E402
from relight_core.data.render import SceneRenderer, init_mitsuba, to_mitsuba_bitmap  # noqa: E402
from relight_core.data.scenes import (CameraSpec, MaterialSpec, ObjectSpec, SceneSpec,  # noqa: E402
                                      camera_to_world, sample_scene)
from tests.factory import main_capturing, terminate_when  # noqa: E402


GREY = MaterialSpec(base_color=(0.5, 0.5, 0.5), texture=None, texture_repeat=1.0, roughness=0.8,
                    metallic=0.0, specular=0.5, transmission=0.0)


@pytest.fixture(scope="module", autouse=True)
def mitsuba_single_thread():
    init_mitsuba(threads=1)


def _scene(objects=(), camera=None, yaw=0.0, ground=GREY) -> SceneSpec:
    camera = camera or CameraSpec(target=(0.0, 0.5, 0.0), distance=3.0, elevation=10.0, azimuth=25.0,
                                  fov=40.0, orbit=0.0, oscillation=0.0, cycles=1.0)
    probe = ProbeChoice(source="test", seed=0, rotation=yaw, exposure=1.0)
    return SceneSpec("train", 0, 0, 1, (), ground, tuple(objects), (probe, probe), 0.0, camera)


def _sun_probe(direction: np.ndarray, h: int = 64) -> np.ndarray:
    """A dark probe with one small bright sun towards `direction` (file convention)."""
    probe = np.full((h, 2 * h, 3), 0.01, np.float32)
    d = lighting.texel_directions(h, 2 * h).numpy()
    probe[d @ direction > math.cos(math.radians(4.0))] = 2000.0
    return probe


def test_mitsuba_envmap_reads_our_convention_after_conversion():
    import drjit as dr
    import mitsuba as mi

    h = 32
    d_file = lighting.texel_directions(h, 2 * h).numpy()
    probe = (0.5 + 0.5 * d_file) * np.array([1.0, 2.0, 3.0], np.float32)  # smooth, asymmetric
    yaw = 70.0
    emitter = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(to_mitsuba_bitmap(probe)),
                            "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], yaw)})
    rng = np.random.default_rng(0)
    dirs = rng.normal(size=(64, 3))
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    si = dr.zeros(mi.SurfaceInteraction3f, len(dirs))
    si.wi = mi.Vector3f(*(-dirs.T).astype(np.float32))  # the envmap looks up −wi
    mitsuba_radiance = np.asarray(emitter.eval(si)).reshape(3, -1).T
    # World radiance is the file seen through the inverse yaw: file(R_y(−yaw)·d).
    ours = lighting.sample_probe(torch.from_numpy(probe), torch.from_numpy(dirs @ lighting.yaw_matrix(-yaw).numpy().T))
    np.testing.assert_allclose(mitsuba_radiance, ours.numpy(), rtol=0.05, atol=0.05)  # bilinear differences near the poles
    # Without the conversion Mitsuba would be 180° of yaw away: the check above must be able to fail.
    emitter_raw = mi.load_dict({"type": "envmap", "bitmap": mi.Bitmap(probe),
                                "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], yaw)})
    raw = np.asarray(emitter_raw.eval(si)).reshape(3, -1).T
    assert np.abs(raw - ours.numpy()).max() > 0.5


def test_sun_lights_the_facing_side_and_encoding_puts_it_at_env_dir():
    size = 48
    sphere = ObjectSpec("sphere", 0, (0.5, 0.5, 0.5), (0.0, 0.0), 0.0, 0.0, (0.0, 0.0), 0.5, GREY)
    yaw = 40.0
    spec = _scene([sphere], yaw=yaw)
    c2w = camera_to_world(spec, 0)
    right, up = c2w[:, 0], c2w[:, 1]
    sun_world = right * math.cos(math.radians(35)) + up * math.sin(math.radians(35))  # upper right of view
    sun_world /= np.linalg.norm(sun_world)
    sun_file = lighting.yaw_matrix(-yaw).numpy() @ sun_world  # the envmap's to_world is R_y(yaw)
    probe = _sun_probe(sun_file)
    with SceneRenderer(spec, size, spp=16, probes=[probe, probe]) as renderer:
        rgb = renderer.render(0, 0, seed=1)
        panorama = renderer.camera_probe(0, 0)

    # The sphere (centre of the image, radius ~8 px) is lit on its right, not its left.
    luminance = rgb.mean(axis=-1)
    rows = slice(size // 2 - 8, size // 2 - 1)  # upper half of the sphere: only sphere and sky
    right_side = luminance[rows, size // 2 + 2: size // 2 + 8].mean()
    left_side = luminance[rows, size // 2 - 8: size // 2 - 2].mean()
    assert right_side > 3 * left_side

    # The brightest panorama pixel's env_dir, taken back to the world, points at the sun.
    encoded = lighting.encode_lighting(torch.from_numpy(panorama)[None])
    i, j = np.unravel_index(np.argmax(panorama.sum(-1)), panorama.shape[:2])
    env_dir = encoded["env_dir"][0, i, j].numpy()
    angle = math.degrees(math.acos(np.clip(np.dot(c2w @ env_dir, sun_world), -1, 1)))
    assert angle < 10.0, angle
    assert env_dir[0] > 0.5 and env_dir[1] > 0.3  # camera frame: to the right and above


def test_two_lights_share_geometry_and_albedo_is_independent_of_light():
    spec = next(s for s in (sample_scene(3, "train", i, frames=2) for i in range(50)) if "orbit" in s.motion)
    with SceneRenderer(spec, 32, spp=4) as renderer:
        albedo_a, mask_a = renderer.render_aovs(1, seed=9, light=0)
        albedo_b, mask_b = renderer.render_aovs(1, seed=9, light=1)
        rgb_a, rgb_b = renderer.render(1, 0, seed=9), renderer.render(1, 1, seed=9)
        albedo_next, _ = renderer.render_aovs(0, seed=9)
    np.testing.assert_array_equal(mask_a, mask_b)
    np.testing.assert_array_equal(albedo_a, albedo_b)
    assert 0.2 < mask_a.mean() < 1.0  # geometry and some sky
    assert np.abs(rgb_a - rgb_b).mean() > 1e-3  # the lights really differ
    assert np.abs(albedo_a - albedo_next).mean() > 1e-3  # and the camera really orbits


def test_albedo_equals_base_colour_on_a_flat_unshadowed_patch():
    base = (0.8, 0.35, 0.1)
    ground = MaterialSpec(base_color=base, texture=None, texture_repeat=1.0, roughness=0.5, metallic=0.0,
                          specular=0.5, transmission=0.0)
    camera = CameraSpec(target=(0.0, 0.0, 0.0), distance=2.0, elevation=70.0, azimuth=0.0, fov=30.0,
                        orbit=0.0, oscillation=0.0, cycles=1.0)
    spec = _scene([], camera=camera, ground=ground)
    probe = np.ones((16, 32, 3), np.float32)
    with SceneRenderer(spec, 32, spp=4, probes=[probe, probe]) as renderer:
        albedo, mask = renderer.render_aovs(0, seed=0)
    patch = linear_to_srgb(albedo[8:24, 8:24])
    np.testing.assert_allclose(patch, np.broadcast_to(base, patch.shape), atol=1.5 / 255)
    assert mask[8:24, 8:24].min() == 1.0


# ---------------------------------------------------------------- render-data on Ray

RUN = dict(scenes=3, frames=2, size=32, spp=4, seed=11)


def _tree(root):
    """Every file under `root` (hidden lock files aside) → its bytes."""
    files = {}
    for path in sorted(root.rglob("*")):
        if path.is_file() and not path.name.startswith("."):
            files[str(path.relative_to(root))] = path.read_bytes()
    return files


def _render_data(out, *flags):
    argv = ["render-data", "--out", str(out), *[f"--{k}={v}" for k, v in RUN.items()], *flags]
    return main_capturing(argv)


def test_render_data_on_ray_writes_the_same_files_fails_a_scene_alone_and_resumes(ray_address, tmp_path):
    """Scenes as Ray tasks on two workers give the bytes one process gives; a scene whose folder
    cannot be made fails alone with its sentence; the re-run renders that scene only."""
    from relight_core.data.generate import RenderConfig, render_dataset

    reference = tmp_path / "in-process"
    render_dataset(RenderConfig(out=reference, workers=1, **RUN), progress=False)
    out = tmp_path / "ray"
    (out / "train").mkdir(parents=True)
    (out / "train" / "scene_000001").write_text("in the way")  # a file where the scene's folder goes

    code, stdout, stderr = _render_data(out, "--workers=2", f"--ray-address={ray_address}")
    assert code == 1, stderr
    assert stdout.strip() == str(out / "train" / "manifest.json")
    sentence = (f"File exists ({out / 'train' / 'scene_000001'}); free some space or choose another "
                "output folder.")
    assert f"scene_000001 failed: {sentence}" in stderr and "Traceback" not in stderr
    assert "2 of 3 scenes done, 1 failed." in stderr
    with open(out / "train" / "failed.csv", newline="") as f:
        assert list(csv.reader(f)) == [["item", "error"], ["scene_000001", sentence]]
    manifest = json.loads((out / "train" / "manifest.json").read_text())
    assert [s["path"] for s in manifest["samples"]] == ["scene_000000", "scene_000002"]
    expected = _tree(reference)
    got = _tree(out)
    for name in ("scene_000000", "scene_000002"):
        assert {k: v for k, v in got.items() if name in k} == {k: v for k, v in expected.items() if name in k}

    stamps = {p: p.stat().st_mtime_ns for p in (out / "train").glob("scene_00000[02]/**/*")}
    (out / "train" / "scene_000001").unlink()
    code, _, stderr = _render_data(out, "--workers=2", f"--ray-address={ray_address}")
    assert code == 0, stderr
    assert "3 scenes: 2 done, 1 to run." in stderr
    assert {p: p.stat().st_mtime_ns for p in stamps} == stamps  # finished scenes were not rendered again
    assert _tree(out) == expected  # every file, manifest included, as one process writes them


def test_sigterm_inside_mitsubas_render_stops_the_run_instead_of_failing_the_scene(tmp_path):
    """Dr.Jit hands a signal handler's exception back as a RuntimeError caused by it; a SIGTERM that
    lands in `mi.render` must stop render-data (exit 143, "stopped."), not fail one scene and go on."""
    out = tmp_path / "data"
    first_light = out / "train" / "scene_000000" / "env0"  # written after light 0, before light 1's render
    code, err = terminate_when(  # ~1–3 s a light at 400 spp: 0.3 s later the signal lands inside the render
        ["render-data", "--out", out, "--scenes=4", "--frames=1", "--size=96", "--spp=400", "--workers=1"],
        first_light.exists, "started rendering", settle_s=0.3)
    assert code == 128 + signal.SIGTERM, err
    assert "stopped." in err and "failed" not in err and "Traceback" not in err, err
    assert not (out / "train" / "failed.csv").exists()


# ---------------------------------------------------------------- where and how long render-data renders

def _cuda_renders() -> bool:
    from relight_core.data.render import _cuda_problem

    try:
        return _cuda_problem() is None
    finally:
        init_mitsuba(threads=1)  # the probe leaves the CUDA variant selected where it works


def test_a_time_budget_starts_no_scene_after_it_and_the_same_command_renders_the_rest(tmp_path):
    """--minutes: a scene already rendering finishes, none starts after the budget, the exit is clean,
    and running the command again without it renders what is left — the files of an uninterrupted run."""
    out, whole = tmp_path / "budget", tmp_path / "whole"
    run = ["--scenes=2", "--frames=1", "--size=64", "--spp=400", "--seed=5", "--workers=1"]
    # ~1 s a light at 400 spp: the first scene outlasts the 0.3 s, so exactly one is rendered
    code, stdout, stderr = main_capturing(["render-data", "--out", str(out), *run, "--minutes=0.005"])
    assert code == 0, stderr
    assert "0.005 minutes are up: 1 scene not started; the same command renders them." in stderr
    assert "1 of 2 scenes done, 0 failed." in stderr and "Traceback" not in stderr
    manifest = json.loads((out / "train" / "manifest.json").read_text())
    assert [s["path"] for s in manifest["samples"]] == ["scene_000000"]
    assert not (out / "train" / "scene_000001").exists()
    code, _, stderr = main_capturing(["render-data", "--out", str(out), *run])
    assert code == 0, stderr
    assert "2 scenes: 1 done, 1 to run." in stderr and "minutes are up" not in stderr
    code, _, stderr = main_capturing(["render-data", "--out", str(whole), *run])
    assert code == 0, stderr
    assert _tree(out) == _tree(whole)


def test_a_time_budget_on_ray_lets_the_running_scene_finish_and_sends_no_other(ray_address, tmp_path):
    """The same budget through Ray tasks: the scene sent before the budget ran out finishes, none is sent after."""
    out = tmp_path / "ray-budget"
    code, _, stderr = main_capturing(["render-data", "--out", str(out), "--scenes=3", "--frames=1", "--size=64",
                                      "--spp=400", "--seed=5", "--workers=1", f"--ray-address={ray_address}",
                                      "--minutes=0.005"])
    assert code == 0, stderr
    assert "0.005 minutes are up: 2 scenes not started; the same command renders them." in stderr
    assert "1 of 3 scenes done, 0 failed." in stderr and "Traceback" not in stderr
    assert [s["path"] for s in json.loads((out / "train" / "manifest.json").read_text())["samples"]] == \
        ["scene_000000"]


def test_the_device_is_recorded_and_a_gpu_where_none_renders_is_one_sentence(tmp_path):
    """Each scene's meta.json names the Mitsuba variant that rendered it; --device cuda where Mitsuba's CUDA
    variant cannot render ends with one sentence and exit 2 before anything is written."""
    out = tmp_path / "data"
    code, _, stderr = main_capturing(["render-data", "--out", str(out), *[f"--{k}={v}" for k, v in RUN.items()],
                                      "--scenes=1", "--workers=1", "--device=cpu"])
    assert code == 0, stderr
    meta = json.loads((out / "train" / "scene_000000" / "meta.json").read_text())
    assert meta["render"]["variant"] == "llvm_ad_rgb"
    if _cuda_renders():
        pytest.skip("Mitsuba renders on a CUDA GPU here (test_cuda_renders_the_scenes_the_cpu_renders covers it)")
    code, stdout, stderr = main_capturing(["render-data", "--out", str(tmp_path / "gpu"), "--scenes=1",
                                           "--frames=1", "--size=32", "--spp=4", "--device=cuda"])
    assert code == 2 and stdout == ""
    assert stderr.startswith("error: Mitsuba cannot render on a CUDA GPU here (") and stderr.count("\n") == 1, stderr
    assert "render with --device cpu" in stderr and "Traceback" not in stderr
    assert not (tmp_path / "gpu").exists()
    code, _, stderr = main_capturing(["render-data", "--out", str(tmp_path / "auto"), "--scenes=1", "--frames=1",
                                      "--size=32", "--spp=4", "--workers=1", "--device=auto", "--quiet"])
    assert code == 0, stderr
    meta = json.loads((tmp_path / "auto" / "train" / "scene_000000" / "meta.json").read_text())
    assert meta["render"]["variant"] == "llvm_ad_rgb"  # auto: the CPU where no GPU renders


def test_on_a_cluster_the_device_is_its_gpus(ray_address, tmp_path):
    """With --ray-address the cluster's GPUs decide, not this machine's: auto renders on its CPUs when it has
    none (and says so), cuda is refused in one sentence."""
    code, _, stderr = _render_data(tmp_path / "auto", "--scenes=1", f"--ray-address={ray_address}", "--device=auto")
    assert code == 0, stderr
    assert "render-data: --device auto renders on the CPU." in stderr
    meta = json.loads((tmp_path / "auto" / "train" / "scene_000000" / "meta.json").read_text())
    assert meta["render"]["variant"] == "llvm_ad_rgb"
    code, _, stderr = _render_data(tmp_path / "cuda", "--scenes=1", f"--ray-address={ray_address}", "--device=cuda")
    assert code == 2
    assert stderr == ("error: GPU workers were asked for (--device cuda), but the Ray cluster has no GPU; run with "
                      "--device cpu or add GPU nodes.\n")


def test_cuda_renders_the_scenes_the_cpu_renders(tmp_path):
    """On a machine whose GPU Mitsuba can use: the same seed gives the same scenes on the GPU as on the CPU,
    their images equal to well within the render noise (the same sampler streams; the film's summation order
    differs)."""
    if not _cuda_renders():
        pytest.skip("Mitsuba cannot render on a CUDA GPU on this machine")
    from relight_core.data.dataset import read_stream
    from relight_core.evaluation.metrics import psnr

    run = ["--scenes=2", "--frames=1", "--size=64", "--spp=64", "--seed=3", "--workers=1", "--quiet"]
    for device in ("cpu", "cuda"):
        code, _, stderr = main_capturing(["render-data", "--out", str(tmp_path / device), *run, f"--device={device}"])
        assert code == 0, stderr
    for i in range(2):
        cpu, gpu = (tmp_path / d / "train" / f"scene_{i:06d}" for d in ("cpu", "cuda"))
        meta_cpu, meta_gpu = (json.loads((p / "meta.json").read_text()) for p in (cpu, gpu))
        assert meta_gpu["render"]["variant"] == "cuda_ad_rgb" and meta_cpu["scene"] == meta_gpu["scene"]
        for name in ("rgb0", "rgb1", "albedo"):
            assert psnr(read_stream(gpu, name, [0]), read_stream(cpu, name, [0])) > 32.0, (i, name)
