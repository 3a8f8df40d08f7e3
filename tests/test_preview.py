"""The light preview shows exactly the light the model is given (same rotation, same convention)."""

import math

import numpy as np
import pytest
import torch

from relight_core import lighting, preview

CONFIG = preview.PreviewConfig(ball_size=128, mirror_resolution=128, diffuse_resolution=32)


def spot_probe(direction, height=128, sigma_deg=4.0, peak=400.0, ambient=0.05) -> torch.Tensor:
    """A dim uniform probe with one bright Gaussian spot around a world direction."""
    texels = lighting.texel_directions(height, 2 * height)                       # [h, 2h, 3]
    d = torch.tensor(direction, dtype=torch.float32)
    angle = torch.acos((texels @ (d / d.norm())).clamp(-1, 1))
    spot = peak * torch.exp(-(angle / math.radians(sigma_deg)) ** 2 / 2)
    return (ambient + spot)[..., None].expand(height, 2 * height, 3).contiguous()


def expected_spot_direction(probe, rotation) -> np.ndarray:
    """Where the model sees the spot: env_dir at the brightest pixel of its camera-frame panorama."""
    panorama = lighting.probe_in_camera(probe, 64, 128, rotation=rotation)      # [64, 128, 3]
    env_dir = lighting.encode_lighting(panorama[None])["env_dir"][0]            # [64, 128, 3]
    row, col = np.unravel_index(int(panorama[..., 0].argmax()), panorama.shape[:2])
    d = env_dir[row, col].numpy()
    return d / np.linalg.norm(d)


def highlight_direction(balls: np.ndarray) -> tuple[np.ndarray, tuple[float, float]]:
    """The mirror direction at the centroid of the saturated highlight on the left (mirror) ball."""
    size = balls.shape[0]
    mirror = balls[:, :size].astype(np.float32).mean(axis=2)
    rows, cols = np.nonzero(mirror >= mirror.max() - 8)
    row, col = rows.mean(), cols.mean()
    return preview.ball_pixel_direction(row, col, size, CONFIG.margin), (row, col)


def angle_deg(a, b) -> float:
    return math.degrees(math.acos(float(np.clip(np.dot(a, b) / np.linalg.norm(a) / np.linalg.norm(b), -1, 1))))


def test_camera_radiance_is_the_model_panorama():
    """The look-up every preview colour comes from is the one that builds the model's panorama."""
    probe = spot_probe((0.3, 0.5, -0.8))
    for rotation in (0.0, 37.5, 180.0, 290.0):
        directions = lighting.panorama_directions(32, 64).reshape(-1, 3)
        ours = lighting.camera_radiance(probe, directions, rotation).reshape(32, 64, 3)
        expected = lighting.probe_in_camera(probe, 32, 64, rotation=rotation)
        torch.testing.assert_close(ours, expected, rtol=1e-5, atol=1e-6)  # float summation order only


def test_mirror_ball_highlight_follows_env_dir_across_rotations():
    probe = spot_probe((0.0, 0.5, -math.sqrt(0.75)))  # 30° up, straight ahead in the file
    checked, positions = 0, []
    for rotation in range(0, 360, 45):
        expected = expected_spot_direction(probe, rotation)
        if expected[2] < -0.5:  # within 60° of the camera's forward: squeezed onto the ball's rim
            continue
        seen, position = highlight_direction(preview.render_balls(probe, rotation, CONFIG))
        assert angle_deg(seen, expected) < 8.0, (rotation, seen, expected)
        positions.append(position)
        checked += 1
    assert checked >= 4
    # The highlight really moves: no two checked rotations put it in the same place.
    spread = [np.hypot(a[0] - b[0], a[1] - b[1]) for i, a in enumerate(positions) for b in positions[i + 1:]]
    assert min(spread) > 5


def test_diffuse_ball_is_brightest_facing_the_light():
    probe = spot_probe((1.0, 0.0, 0.0), peak=2000.0)  # a sun on the +X side of the file
    for rotation, lit_side in ((0.0, "right"), (180.0, "left")):
        balls = preview.render_balls(probe, rotation, CONFIG)
        size = balls.shape[0]
        diffuse = balls[:, size:].astype(np.float32).mean(axis=2)
        left, right = diffuse[size // 2, size // 5], diffuse[size // 2, 4 * size // 5]
        assert (right > left + 20) if lit_side == "right" else (left > right + 20), (rotation, left, right)


def test_uniform_light_gives_uniform_diffuse_ball_of_albedo():
    probe = torch.ones(32, 64, 3)
    normals = torch.nn.functional.normalize(torch.randn(50, 3), dim=1)
    radiance = 0.8 * lighting.diffuse_radiance(probe, normals, 0.0, height=32)
    torch.testing.assert_close(radiance, torch.full_like(radiance, 0.8), atol=0.02, rtol=0)
    # ...and the preview's matte ball shows exactly that shading: 0.8 of uniform light 4.0 in the middle.
    balls = preview.render_balls(torch.full((16, 32, 3), 4.0), 0.0, CONFIG)
    size = CONFIG.ball_size
    expected = preview.to_display(torch.tensor([[3.2, 3.2, 3.2]]))[0].astype(int)
    middle = balls[size // 2 - 4:size // 2 + 4, size + size // 2 - 4:size + size // 2 + 4].reshape(-1, 3)
    assert np.abs(middle.astype(int) - expected).max() <= 2, (middle.mean(axis=0), expected)


def test_preview_image_layout_and_forward_marker():
    probe = spot_probe((0.0, 0.0, -1.0))  # the spot sits straight ahead of the camera at rotation 0
    image = preview.render_preview(probe, rotation=0.0, config=CONFIG)
    size = CONFIG.ball_size
    assert image.shape == (2 * size, 2 * size, 3) and image.dtype == np.uint8
    strip = image[size:]
    # The marker is drawn at the panorama's centre, where the spot is at rotation 0.
    assert tuple(strip[size // 2, size]) == (255, 64, 32)
    with pytest.raises(AssertionError):
        np.testing.assert_array_equal(image, preview.render_preview(probe, rotation=90.0, config=CONFIG))


def test_probe_thumbnail_keeps_a_small_sun():
    probe = torch.zeros(256, 512, 3)
    probe[100, 300] = 5000.0  # one texel sun must survive the downsampling
    thumb = preview.probe_thumbnail(probe, 32)
    assert thumb.shape == (32, 64, 3) and thumb.max() > 100




def test_ball_rims_are_antialiased():
    # Under uniform light a ball is one flat colour, so any pixel between it and the background lies on
    # the rim, partly covered. An aliased render has few, in a handful of levels (EGL's 4× multisampling
    # alone gives ~0.55 of the circumference in 3 levels); a supersampled one rings the ball with a
    # smooth ramp.
    balls = preview.render_balls(torch.full((16, 32, 3), 4.0), 0.0, CONFIG)
    size = CONFIG.ball_size
    for ball in (balls[:, :size], balls[:, size:]):
        grey = ball.astype(np.float32).mean(axis=2)
        background, inside = grey[1, 1], grey[size // 2, size // 2]
        low, high = sorted((background, inside))
        margin = 0.15 * (high - low)
        partial = (grey > low + margin) & (grey < high - margin)
        circumference = 2 * math.pi * (size / 2) / CONFIG.margin
        assert partial.sum() > 0.9 * circumference, (partial.sum(), circumference)
        assert np.unique(grey[partial]).size > 20
