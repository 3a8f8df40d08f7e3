"""Real test files made on the spot: PNG, MP4 (with and without audio), EXR probes."""

from __future__ import annotations

from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import OpenEXR
from PIL import Image


def make_png(path: Path, width: int = 48, height: int = 32, seed: int = 0) -> Path:
    """A smooth colour gradient with some noise, saved as 8-bit RGB PNG."""
    rng = np.random.default_rng(seed)
    y, x = np.mgrid[0:height, 0:width]
    img = np.stack([x / width, y / height, 0.5 + 0.3 * np.sin(x / 5.0)], -1)
    img = np.clip(img + 0.05 * rng.standard_normal(img.shape), 0, 1)
    Image.fromarray((img * 255).astype(np.uint8)).save(path)
    return path


def make_mp4(path: Path, frames: int = 12, width: int = 48, height: int = 32, fps: int = 12,
             audio: bool = False) -> Path:
    """A moving gradient encoded with libx264; optionally with a 440 Hz AAC tone."""
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=fps)
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        audio_stream = container.add_stream("aac", rate=22050) if audio else None
        for i in range(frames):
            y, x = np.mgrid[0:height, 0:width]
            img = np.stack([(x + 3 * i) % width / width, y / height, np.full_like(x, i / max(frames, 1), float)], -1)
            frame = av.VideoFrame.from_ndarray((img * 255).astype(np.uint8), format="rgb24")
            for packet in stream.encode(frame):
                container.mux(packet)
        for packet in stream.encode():
            container.mux(packet)
        if audio_stream is not None:
            samples = int(22050 * frames / fps)
            tone = (0.2 * np.sin(2 * np.pi * 440 * np.arange(samples) / 22050)).astype(np.float32)
            chunk = 1024
            for start in range(0, samples, chunk):
                part = tone[start:start + chunk][None]
                frame = av.AudioFrame.from_ndarray(part, format="fltp", layout="mono")
                frame.sample_rate = 22050
                frame.pts = start
                frame.time_base = Fraction(1, 22050)
                for packet in audio_stream.encode(frame):
                    container.mux(packet)
            for packet in audio_stream.encode():
                container.mux(packet)
    return path


def write_exr(path: Path, rgb: np.ndarray) -> Path:
    """Write a float32 [H,W,3] array as an RGB EXR."""
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    with OpenEXR.File(header, {"RGB": np.ascontiguousarray(rgb, dtype=np.float32)}) as f:
        f.write(str(path))
    return path


def make_sun_probe(path: Path, width: int = 64, height: int = 32) -> Path:
    """A dim blue sky with one small bright sun, as EXR."""
    env = np.zeros((height, width, 3), np.float32)
    env[: height // 2] = [0.3, 0.4, 0.6]
    env[height // 2:] = [0.2, 0.18, 0.15]
    env[height // 4, width // 4] = [800.0, 760.0, 700.0]
    return write_exr(path, env)


def record_encoded_lighting(monkeypatch) -> list:
    """The camera-frame panoramas the pipeline hands `lighting.encode_lighting`, in call order."""
    from relight_core import lighting

    seen = []
    encode = lighting.encode_lighting
    monkeypatch.setattr(lighting, "encode_lighting", lambda env: seen.append(env.clone()) or encode(env))
    return seen


def lighting_the_preview_shows(relighter, light, like, *view):
    """The preview's camera-frame lookup of `light` (rotation[, camera]) on the grid of the encoded
    panorama `like`, seen through the model's lighting grid: what the model must be given."""
    from relight_core import lighting, preview

    height, width = like.shape[1:3]
    directions = lighting.panorama_directions(height, width).reshape(-1, 3)
    shown = preview.camera_radiance(light, directions, *view)
    return lighting.lowpass_panorama(shown.reshape(1, height, width, 3), relighter.spec.lighting_size)
