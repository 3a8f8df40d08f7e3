"""Lighting: conventions, released sampling, rotation, encodings, balls and probe files."""

import math
import os

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")

import cv2  # noqa: E402
import numpy as np  # noqa: E402
import OpenEXR  # noqa: E402
import pytest  # noqa: E402
import torch  # noqa: E402
from PIL import Image  # noqa: E402

from relight_core.errors import InputError  # noqa: E402
from relight_core.lighting import (  # noqa: E402
    DEFAULT_ROTATION,
    clean_hdr,
    diffuse_ball,
    diffuse_radiance,
    direction_to_uv,
    encode_lighting,
    latlong_directions,
    load_probe,
    mirror_ball,
    mirror_ball_to_latlong,
    panorama_directions,
    probe_frames,
    probe_in_camera,
    roll_probe,
    rotate_probe,
    rotation_sweep,
    sample_probe,
    texel_directions,
    tonemap_display,
    uv_to_direction,
    yaw_matrix,
)


def srgb(x: float) -> float:
    return 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055


def lobe_probe(sun, h=128, w=256, sharpness=40.0) -> torch.Tensor:
    """A smooth bright lobe around direction `sun`, evaluated analytically at texel centres."""
    sun = torch.nn.functional.normalize(torch.tensor(sun, dtype=torch.float32), dim=0)
    value = torch.exp(sharpness * (texel_directions(h, w) @ sun - 1))  # [h, w]
    return value[..., None].repeat(1, 1, 3)


def lobe(directions, sun, sharpness=40.0) -> torch.Tensor:
    sun = torch.nn.functional.normalize(torch.tensor(sun, dtype=torch.float32), dim=0)
    return torch.exp(sharpness * (torch.nn.functional.normalize(directions, dim=-1) @ sun - 1))


def write_exr(path, rgb: np.ndarray, half=False) -> None:
    data = rgb.astype(np.float16 if half else np.float32)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"RGB": data}).write(str(path))


# ---------------------------------------------------------------------------------------------
# Geometry and conventions
# ---------------------------------------------------------------------------------------------


def test_direction_uv_convention():
    d = torch.tensor([[0, 0, -1], [1, 0, 0], [-1, 0, 0], [0, 1, 0], [0, -1, 0]], dtype=torch.float32)
    uv = direction_to_uv(d)
    assert torch.allclose(uv[0], torch.tensor([0.5, 0.5]))  # file centre looks down −Z
    assert torch.allclose(uv[1], torch.tensor([0.75, 0.5]))
    assert torch.allclose(uv[2], torch.tensor([0.25, 0.5]))
    assert uv[3, 1] == 0.0 and uv[4, 1] == 1.0  # row 0 straight up
    grid = texel_directions(8, 16)
    assert torch.allclose(uv_to_direction(direction_to_uv(grid)), grid, atol=1e-6)


def test_released_grids():
    H, W = 6, 8
    d = latlong_directions(H, W)
    theta = math.pi * (1 / H)  # released first row is at θ = π/H, not π/(2H)
    phi = math.pi * (-1 + 1 / W)
    expected = torch.tensor([math.sin(theta) * math.sin(phi), math.cos(theta), -math.sin(theta) * math.cos(phi)])
    assert torch.allclose(d[0, 0], expected, atol=1e-6)
    # env_dir is the released envmap_vec = −latlong_vec.flip(0).flip(1).
    assert torch.allclose(panorama_directions(H, W), -d.flip(0).flip(1), atol=1e-6)


def test_encode_lighting_hand_computed():
    x = torch.tensor([0.0, 1e-4, 1.0, 16.0, 1000.0, 10000.0, 65504.0]).reshape(1, 1, 7, 1).repeat(1, 1, 1, 3)
    out = encode_lighting(x)
    reinhard = [0.0, 1e-4 * (1 + 1e-4 / 256) / (1 + 1e-4), 1 * (1 + 1 / 256) / 2, 1.0, 1.0, 1.0, 1.0]
    ldr = [2 * srgb(r) - 1 for r in reinhard]
    log = [2 * min(srgb(math.log1p(v) / math.log1p(10000)), 1.0) - 1 for v in [0, 1e-4, 1, 16, 1000, 10000, 65504]]
    assert ldr[0] == -1 and ldr[3] == pytest.approx(1.0) and ldr[2] == pytest.approx(0.473284, abs=1e-6)
    assert torch.allclose(out["env_ldr"][0, 0, :, 0], torch.tensor(ldr, dtype=torch.float32), atol=1e-5)
    assert torch.allclose(out["env_log"][0, 0, :, 0], torch.tensor(log, dtype=torch.float32), atol=1e-5)
    assert out["env_log"][0, 0, 5, 0] == pytest.approx(1.0, abs=1e-6)  # log1p(10000)/log1p(10000) = 1
    for value in out.values():
        assert value.shape == (1, 1, 7, 3) and value.dtype == torch.float32


def test_env_dir_unit_length_and_layout():
    env = torch.rand(2, 16, 32, 3)
    env_dir = encode_lighting(env)["env_dir"]
    assert env_dir.shape == (2, 16, 32, 3)
    assert torch.allclose(env_dir.norm(dim=-1), torch.ones(2, 16, 32), atol=1e-6)
    assert env_dir[0, 8, 16, 2] > 0.99  # centre column is camera +Z
    assert env_dir[0, 8, 0, 2] < -0.99  # edge columns are camera −Z
    assert env_dir[0, 0, :, 1].min() > 0.98  # top row is +Y


# ---------------------------------------------------------------------------------------------
# Sampling and rotation
# ---------------------------------------------------------------------------------------------


def test_sampling_wraps_across_the_seam():
    probe = torch.zeros(4, 8, 3)
    probe[:, 0] = 1.0  # first column; the last stays 0
    # +Z sits exactly on the seam u = 0 ≡ 1, half-way between the last and first texel centres.
    assert torch.allclose(sample_probe(probe, torch.tensor([[0.0, 0.0, 1.0]])), torch.full((1, 3), 0.5))


@pytest.mark.parametrize("k", [1, 5, 8, -3])
def test_rotation_by_whole_columns_equals_roll(k):
    probe = torch.rand(16, 64, 3)
    degrees = 360.0 / 64 * k
    assert torch.allclose(rotate_probe(probe, degrees), torch.roll(probe, k, dims=1), atol=1e-4)
    if k in (1, 8):  # int() in the released roll is exact here
        assert torch.equal(roll_probe(probe, degrees), torch.roll(probe, k, dims=1))
        assert torch.allclose(rotate_probe(probe, degrees), roll_probe(probe, degrees), atol=1e-4)


def test_rotation_moves_light_towards_plus_u_at_sub_column_angles():
    probe = torch.zeros(16, 64, 3)
    probe[8, 32] = 1.0  # texel centre u = 32.5/64, just right of −Z
    rotated = rotate_probe(probe, 45.0 + 360.0 / 64 / 2)[..., 0]  # 8.5 columns
    columns = torch.arange(64, dtype=torch.float32)
    assert rotated.sum() == pytest.approx(1.0, abs=1e-5)
    assert (rotated.sum(0) * columns).sum() == pytest.approx(40.5, abs=1e-4)
    # The convention: out(d) = probe(R_y(a)·d), so the light moves from d to R_y(a)ᵀ·d.
    sun = uv_to_direction(torch.tensor([32.5 / 64, 8.5 / 16]))
    moved = sun @ yaw_matrix(90.0)  # row form of R_y(90)ᵀ·sun
    assert direction_to_uv(moved)[0] == pytest.approx(32.5 / 64 + 0.25, abs=1e-6)


def test_rotation_sweep_includes_endpoint():
    assert rotation_sweep(5) == [0.0, 90.0, 180.0, 270.0, 360.0]
    assert rotation_sweep(3, 10.0, 30.0) == [10.0, 20.0, 30.0]
    assert rotation_sweep(1) == [0.0]


def test_probe_in_camera_matches_the_analytic_lookup():
    sun = (1.0, 0.3, -0.2)
    probe = lobe_probe(sun)
    H, W = 24, 40
    # Hand-built camera-frame grid: released θ/φ, and e = (sinθ sinφ, cosθ, +sinθ cosφ).
    theta = math.pi * torch.linspace(1 / H, 1 - 1 / H, H)
    phi = math.pi * torch.linspace(-1 + 1 / W, 1 - 1 / W, W)
    t, p = torch.meshgrid(theta, phi, indexing="ij")
    e = torch.stack((t.sin() * p.sin(), t.cos(), t.sin() * p.cos()), dim=-1)
    pitch = torch.tensor([[1.0, 0.0, 0.0], [0.0, 0.0, -1.0], [0.0, 1.0, 0.0]])  # 90° about +X
    for rotation, cam in [(0.0, None), (DEFAULT_ROTATION, None), (30.0, pitch)]:
        c2w = torch.eye(3) if cam is None else cam
        world = e @ c2w.T @ yaw_matrix(rotation).T
        got = probe_in_camera(probe, H, W, rotation, cam)[..., 0]
        assert torch.allclose(got, lobe(world, sun), atol=0.03), rotation


def test_probe_in_camera_spot_position():
    probe = lobe_probe((1.0, 0.0, 0.0), sharpness=200.0)  # sun at +X: file column 0.75·w
    H, W = 33, 64
    # rotation 0: pixel e = +X, φ = π/2, i.e. column 0.75·W − 0.5 = 47.5; the equator is row 16.
    pano = probe_in_camera(probe, H, W, rotation=0.0)[..., 0]
    row, col = divmod(int(pano.argmax()), W)
    assert row == 16 and col in (47, 48)
    # Default 180°: the file is mirrored left-right, the sun shows at camera −X, column 15.5.
    pano = probe_in_camera(probe, H, W)[..., 0]
    row, col = divmod(int(pano.argmax()), W)
    assert row == 16 and col in (15, 16)


def test_camera_yaw_equals_light_rotation():
    probe = torch.rand(32, 64, 3)
    a = probe_in_camera(probe, 16, 32, rotation=0.0, cam_to_world=yaw_matrix(70.0))
    b = probe_in_camera(probe, 16, 32, rotation=70.0)
    assert torch.allclose(a, b, atol=1e-4)


def test_probe_frames_sweep_and_static():
    probe = torch.rand(32, 64, 3)
    static = probe_frames(probe, 3, 8, 16, rotation=30.0)
    assert static.shape == (3, 8, 16, 3)
    assert torch.equal(static[0], static[2])
    swept = probe_frames(probe, 5, 8, 16, rotation=30.0, rotate_light=True)
    assert torch.allclose(swept[0], probe_in_camera(probe, 8, 16, 30.0), atol=1e-5)
    assert torch.allclose(swept[2], probe_in_camera(probe, 8, 16, 210.0), atol=1e-5)
    assert torch.allclose(swept[4], swept[0], atol=1e-4)  # 360° included: last equals first
    assert not torch.allclose(swept[1], swept[0], atol=1e-2)
    cams = torch.stack([yaw_matrix(0.0), yaw_matrix(90.0)])
    per_camera = probe_frames(probe, 2, 8, 16, rotation=0.0, cam_to_world=cams)
    assert torch.allclose(per_camera[1], probe_in_camera(probe, 8, 16, 90.0), atol=1e-4)


# ---------------------------------------------------------------------------------------------
# Balls
# ---------------------------------------------------------------------------------------------


def ball_pixel(n, size):
    """(row, col) of the ball pixel whose normal is n (grid x = linspace(−1, 1), y = linspace(1, −1))."""
    return (1 - n[1]) / 2 * (size - 1), (n[0] + 1) / 2 * (size - 1)


@pytest.mark.parametrize(
    "sun, rotation, expected_normal",
    [
        ((1.0, 0.0, 0.0), 0.0, (math.sqrt(0.5), 0.0)),  # light at camera right: right of the ball
        ((0.0, 1.0, 0.0), 123.0, (0.0, math.sqrt(0.5))),  # light overhead: top, whatever the yaw
        ((1.0, 0.0, 0.0), 90.0, (0.0, 0.0)),  # R_y(90)ᵀ·(+X) = +Z: behind the camera, ball centre
        ((0.0, 0.0, -1.0), DEFAULT_ROTATION, (0.0, 0.0)),  # file centre at 180°: ball centre
    ],
)
def test_mirror_ball_highlight_is_the_reflection(sun, rotation, expected_normal):
    size = 65
    image, mask = mirror_ball(lobe_probe(sun, sharpness=300.0), size, rotation=rotation)
    assert image.shape == (size, size, 3) and mask.shape == (size, size) and mask.dtype == torch.bool
    row, col = divmod(int(image[..., 0].argmax()), size)
    expected_row, expected_col = ball_pixel(expected_normal, size)
    assert abs(row - expected_row) <= 1 and abs(col - expected_col) <= 1
    assert image[~mask].abs().max() == 0


def test_mirror_ball_round_trip():
    sun = (0.3, 0.5, -0.8)
    probe = 0.2 + lobe_probe(sun, h=32, w=64, sharpness=4.0)  # smooth light
    for rotation in (DEFAULT_ROTATION, 40.0):
        ball, _ = mirror_ball(probe, 384, rotation=rotation)
        back = mirror_ball_to_latlong(ball, 32, 64, rotation=rotation)
        camera = texel_directions(32, 64) @ yaw_matrix(rotation)  # world → camera frame
        seen = camera[..., 2] > -0.5  # away from the back pole, where the ball squeezes everything
        assert seen.float().mean() > 0.6
        assert (back - probe)[seen].abs().max() < 0.03


def test_diffuse_ball_uniform_and_sun():
    image, mask = diffuse_ball(torch.ones(32, 64, 3), 64)
    assert torch.allclose(image[mask], torch.ones(int(mask.sum()), 3), atol=0.02)  # white furnace
    assert image[~mask].abs().max() == 0
    image, mask = diffuse_ball(lobe_probe((0.0, 0.0, 1.0), sharpness=100.0), 65, rotation=90.0)
    # R_y(90)ᵀ·(+Z) = −X: light from the camera's left lights the left of the ball.
    row, col = divmod(int(image[..., 0].argmax()), 65)
    assert col < 10 and abs(row - 32) <= 3
    assert image[32, 60, 0] < 0.05 * image[row, col, 0]


def test_diffuse_shading_keeps_the_energy_of_small_bright_lights():
    """Studio lamps a few texels wide: the shading equals the cosine-weighted sum over every texel of
    the full-size probe, (1/π)Σ L·max(0, n·ω)·dω, to 2 % (the preview's former copy, which point-sampled
    a coarse grid instead of area-averaging it, was 56 % and 187 % off here)."""
    h, w = 128, 256
    probe = torch.full((h, w, 3), 0.05)
    rng = np.random.default_rng(0)
    for row, col in zip(rng.integers(16, h - 16, 6), rng.integers(0, w - 2, 6)):
        probe[row:row + 2, col:col + 2] = 2000.0
    normals = torch.nn.functional.normalize(torch.from_numpy(rng.standard_normal((300, 3))).float(), dim=1)
    theta = (torch.arange(h) + 0.5) * math.pi / h
    solid_angle = (torch.sin(theta) * (math.pi / h) * (2 * math.pi / w)).repeat_interleave(w)       # [h·w]
    for rotation in (0.0, 75.0):
        world = normals @ yaw_matrix(rotation).T
        cosine = (world @ texel_directions(h, w).reshape(-1, 3).T).clamp(min=0)                       # [300, h·w]
        expected = cosine @ (probe.reshape(-1, 3) * solid_angle[:, None]) / math.pi
        shaded = diffuse_radiance(probe, normals, rotation)
        error = ((shaded - expected).abs().sum(dim=1) / expected.sum(dim=1)).mean()
        assert error < 0.02, (rotation, float(error))


# ---------------------------------------------------------------------------------------------
# Files, cleaning, errors
# ---------------------------------------------------------------------------------------------


def test_exr_round_trip(tmp_path):
    rgb = np.random.default_rng(0).uniform(0, 50, (8, 16, 3)).astype(np.float32)
    rgb[0, 0] = (5.0, 0.0, 0.0)  # channel order check
    write_exr(tmp_path / "p.exr", rgb)
    probe = load_probe(tmp_path / "p.exr")
    assert probe.dtype == torch.float32 and probe.shape == (8, 16, 3)
    assert torch.equal(probe, torch.from_numpy(rgb))
    write_exr(tmp_path / "half.exr", rgb, half=True)
    assert torch.allclose(load_probe(tmp_path / "half.exr"), torch.from_numpy(rgb), rtol=1e-3)
    assert torch.allclose(load_probe(tmp_path / "p.exr", intensity=2.0), 2 * torch.from_numpy(rgb))


def test_greyscale_exr(tmp_path):
    y = np.full((4, 8), 3.0, np.float32)
    OpenEXR.File({"type": OpenEXR.scanlineimage}, {"Y": y}).write(str(tmp_path / "y.exr"))
    assert torch.equal(load_probe(tmp_path / "y.exr"), torch.full((4, 8, 3), 3.0))


def test_hdr_round_trip(tmp_path):
    rgb = np.random.default_rng(1).uniform(0.1, 50, (8, 16, 3)).astype(np.float32)
    rgb[0, 0] = (5.0, 0.0, 0.0)
    assert cv2.imwrite(str(tmp_path / "p.hdr"), rgb[..., ::-1])  # OpenCV writes BGR
    probe = load_probe(tmp_path / "p.hdr").numpy()
    # RGBE shares one exponent per pixel: 8 bits of mantissa relative to the brightest channel.
    assert (np.abs(probe - rgb) <= rgb.max(-1, keepdims=True) / 100).all()
    assert probe[0, 0, 0] > 4.9 and probe[0, 0, 2] == 0


def test_nan_inf_cleaned(tmp_path):
    rgb = np.ones((4, 8, 3), np.float32)
    rgb[0, 0] = (np.nan, np.inf, -np.inf)
    rgb[0, 1] = (-3.0, 1e6, 40000.0)
    write_exr(tmp_path / "bad.exr", rgb)
    probe = load_probe(tmp_path / "bad.exr", intensity=2.0)
    assert probe[0, 0].tolist() == [0.0, 65504.0, 0.0]  # released: NaN→0, +Inf→65504, −Inf→0
    assert probe[0, 1].tolist() == [0.0, 65504.0, 65504.0]  # intensity first, then the clamp
    assert probe[1, 1].tolist() == [2.0, 2.0, 2.0]
    assert torch.isfinite(clean_hdr(torch.tensor([float("nan")]))).all()


@pytest.mark.parametrize("content", ["nan", "zero"])
def test_probe_without_light_is_refused(tmp_path, content):
    rgb = np.full((4, 8, 3), np.nan if content == "nan" else 0.0, np.float32)
    write_exr(tmp_path / "dark.exr", rgb)
    with pytest.raises(InputError, match="no finite light"):
        load_probe(tmp_path / "dark.exr")


def test_bad_files_raise_input_error(tmp_path):
    rgb = np.random.default_rng(2).uniform(0, 5, (64, 128, 3)).astype(np.float32)
    write_exr(tmp_path / "good.exr", rgb)
    data = (tmp_path / "good.exr").read_bytes()
    (tmp_path / "trunc.exr").write_bytes(data[: len(data) // 2])
    cv2.imwrite(str(tmp_path / "good.hdr"), rgb)
    data = (tmp_path / "good.hdr").read_bytes()
    (tmp_path / "trunc.hdr").write_bytes(data[: len(data) // 2])
    (tmp_path / "text.exr").write_text("not an image")
    Image.new("RGB", (8, 4)).save(tmp_path / "png.hdr", format="PNG")
    (tmp_path / "huge.hdr").write_bytes(b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 100000 +X 200000\n" + b"\0" * 64)
    for name in ["trunc.exr", "trunc.hdr", "text.exr", "png.hdr", "huge.hdr", "missing.exr"]:
        with pytest.raises(InputError) as info:
            load_probe(tmp_path / name)
        message = str(info.value)
        assert message.endswith(".") and message.count(". ") == 0, message  # one sentence
    with pytest.raises(InputError):
        load_probe(tmp_path / "good.exr", intensity=-1.0)


def test_tonemap_display():
    probe = torch.tensor([[[0.0, 16.0, 1000.0]]])
    assert tonemap_display(probe).tolist() == [[[0, 255, 255]]]
    assert tonemap_display(probe).dtype == np.uint8


def test_frame_rotations_offset_the_sweep_by_the_chosen_yaw():
    from relight_core.lighting import frame_rotations
    assert frame_rotations(3, 30.0) == [30.0, 30.0, 30.0]
    assert frame_rotations(3, 30.0, rotate_light=True) == [30.0, 210.0, 390.0]
    assert frame_rotations(2, 0.0, rotate_light=True, sweep=(90.0, 180.0)) == [90.0, 180.0]
