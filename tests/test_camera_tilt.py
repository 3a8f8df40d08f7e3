"""Camera pitch and roll: one rotation of the probe, the same for the preview and the model."""

import math

import numpy as np
import pytest
import torch

from relight_core import lighting, preview
from relight_core.cli import main
from relight_core.errors import InputError
from relight_core.pipeline import Relighter, RelightRequest
from tests.factory import lighting_the_preview_shows, make_png, make_sun_probe, record_encoded_lighting


def sky_probe(height: int = 64) -> torch.Tensor:
    """Bright sky above the horizon, dark ground below: a horizon that is easy to find."""
    probe = torch.full((height, 2 * height, 3), 0.05)
    probe[: height // 2] = 4.0
    return probe


def horizon_rows(panorama: torch.Tensor) -> np.ndarray:
    """Per column of a lat-long panorama [h, w, 3], the first row from the top that is dark."""
    dark = (panorama.mean(dim=-1) < 1.0).numpy()
    return dark.argmax(axis=0)


def test_pitch_turns_the_view_up_and_roll_turns_the_camera_counter_clockwise():
    assert torch.equal(lighting.camera_rotation(0, 0), torch.eye(3))
    forward = lighting.camera_rotation(30, 0) @ torch.tensor([0.0, 0.0, -1.0])
    torch.testing.assert_close(forward, torch.tensor([0.0, 0.5, -math.sqrt(0.75)]))
    up = lighting.camera_rotation(0, 90) @ torch.tensor([0.0, 1.0, 0.0])
    torch.testing.assert_close(up, torch.tensor([-1.0, 0.0, 0.0]), atol=1e-6, rtol=0)
    rotation = lighting.camera_rotation(25, -40)
    torch.testing.assert_close(rotation @ rotation.T, torch.eye(3), atol=1e-6, rtol=0)


@pytest.mark.parametrize("pitch, roll", [(91, 0), (0, 181), (float("nan"), 0), (0, float("inf")), ("up", 0)])
def test_absurd_tilts_are_one_sentence(pitch, roll):
    with pytest.raises(InputError, match="camera"):
        lighting.camera_rotation(pitch, roll)


def test_the_preview_horizon_moves_with_the_tilt():
    probe, height = sky_probe(), 64
    level = horizon_rows(preview.camera_panorama(probe, 0.0, height))
    assert np.ptp(level) <= 1 and abs(level.mean() - height / 2) <= 1       # level camera: the horizon is flat
    up = horizon_rows(preview.camera_panorama(probe, 0.0, height, lighting.camera_rotation(20, 0)))
    centre = height                                                         # the column the camera looks along
    assert up[centre] - level[centre] == pytest.approx(20 / 180 * height, abs=1.5)  # looking up: horizon lower
    rolled = horizon_rows(preview.camera_panorama(probe, 0.0, height, lighting.camera_rotation(0, 20)))
    # Turned counter-clockwise, the camera sees the horizon turned clockwise: higher on its left (−X,
    # the columns before the centre), lower on its right, by the roll at 90° either side.
    quarter = height // 2
    assert rolled[centre + quarter] - rolled[centre - quarter] == pytest.approx(2 * 20 / 180 * height, abs=2)


def test_the_model_gets_the_tilted_light_the_preview_shows(monkeypatch):
    relighter = Relighter.load("tiny", device="cpu")
    probe = torch.rand(32, 64, 3) * 4
    seen = record_encoded_lighting(monkeypatch)
    frames = np.random.default_rng(0).random((1, 32, 48, 3), dtype=np.float32)
    request = dict(frames=frames, probe=probe, rotation=30.0, steps=1, sampler="euler")
    relighter.relight(RelightRequest(**request, camera_pitch=15.0, camera_roll=-10.0))
    expected = lighting_the_preview_shows(relighter, lighting.adjust_light(probe), seen[0], 30.0,
                                          lighting.camera_rotation(15, -10))
    torch.testing.assert_close(seen[0], expected, rtol=1e-4, atol=1e-5)
    seen.clear()
    relighter.relight(RelightRequest(**request))
    assert not torch.allclose(seen[0], expected)  # a level camera is given other light
    with pytest.raises(InputError, match="camera pitch"):
        relighter.relight(RelightRequest(**request, camera_pitch=120.0))


def test_preview_balls_move_with_the_tilt():
    config = preview.PreviewConfig(ball_size=64, mirror_resolution=48, diffuse_resolution=24)
    level = preview.render_preview(sky_probe(), 0.0, config=config).astype(float)
    tilted = preview.render_preview(sky_probe(), 0.0, config=config, pitch=30.0).astype(float)
    balls = slice(0, config.ball_size)
    assert np.abs(level[balls] - tilted[balls]).mean() > 2


def test_command_line_tilt_reaches_the_request(tmp_path, monkeypatch, capsys):
    used = []
    rotation = lighting.camera_rotation
    monkeypatch.setattr(lighting, "camera_rotation", lambda pitch=0.0, roll=0.0: used.append((pitch, roll))
                        or rotation(pitch, roll))
    args = ["relight", str(make_png(tmp_path / "photo.png")), "--probe", str(make_sun_probe(tmp_path / "sun.exr")),
            "--model", "tiny", "--steps", "1", "--size", "48"]
    assert main([*args, "--out", str(tmp_path / "a"), "--camera-pitch", "12", "--camera-roll", "-5"]) == 0
    assert used and set(used) == {(12.0, -5.0)}
    assert main([*args, "--out", str(tmp_path / "b"), "--camera-pitch", "95"]) == 2
    assert "camera pitch 95" in capsys.readouterr().err
