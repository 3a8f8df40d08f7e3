"""The shipped default model: it is in the repository, trained, and runs on a CPU."""

import numpy as np

from relight_core import media
from relight_core.checkpoint import DEFAULT_MODEL_DIR, resolve_model
from relight_core.lighting import load_probe
from relight_core.pipeline import Relighter, RelightRequest


def test_default_resolves_to_the_shipped_trained_model():
    spec, directory = resolve_model("default")
    assert directory == DEFAULT_MODEL_DIR and spec.trained


def test_default_model_relights_an_image():
    root = DEFAULT_MODEL_DIR.parent.parent
    relighter = Relighter.load("default", device="cpu")
    frames = media.resize_frames(media.load_media(root / "examples" / "inputs" / "objects.png").frames,
                                 relighter.spec.size)
    probe = load_probe(root / "envmaps" / "sunset.exr")
    result = relighter.relight(RelightRequest(frames, probe=probe, steps=8))
    assert result.relit.shape == frames.shape and np.isfinite(result.relit).all()
    # A trained model keeps the scene: its outputs follow the input pixel by pixel, where an
    # untrained one gives noise (correlation ≈ 0). Measured with the shipped model at 8 steps under
    # this probe: relit +0.56, albedo −0.35 (this early model inverts the bright backdrop's albedo).
    assert np.corrcoef(result.relit.ravel(), frames.ravel())[0, 1] > 0.3
    assert abs(np.corrcoef(result.albedo.ravel(), frames.ravel())[0, 1]) > 0.15
