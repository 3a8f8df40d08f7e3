"""What several test modules share: real files made on the spot (PNG, MP4 with and without audio,
EXR probes, bad uploads), the studio served on a free port with a client's helpers, and stand-ins
for the released Cosmos tokenizer files."""

from __future__ import annotations

import contextlib
import io
import signal
import socket
import subprocess
import sys
import time
from collections.abc import Callable
from fractions import Fraction
from pathlib import Path

import av
import numpy as np
import OpenEXR
import torch
from PIL import Image
from torch import nn

from relight_core import media
from relight_core.data.dataset import write_frame, write_manifest, write_meta
from relight_core.dit import DiTConfig

REPO = Path(__file__).resolve().parent.parent
UPLOAD_LIMIT_MB = 1  # the studio's upload limit in these tests


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
    from relight_core import lighting

    height, width = like.shape[1:3]
    directions = lighting.panorama_directions(height, width).reshape(-1, 3)
    shown = lighting.camera_radiance(light, directions, *view)
    return lighting.lowpass_panorama(shown.reshape(1, height, width, 3), relighter.spec.lighting_size)


def scene_image(path: Path, size=(96, 64)) -> Path:
    """A small real picture: smooth gradients and a few shapes, saved as PNG."""
    w, h = size
    yy, xx = np.mgrid[0:h, 0:w] / np.array([h, w])[:, None, None]
    image = np.stack([0.2 + 0.6 * xx, 0.3 + 0.5 * yy, 0.5 + 0.3 * xx * yy], axis=-1)
    image[(xx - 0.3) ** 2 + (yy - 0.5) ** 2 < 0.04] = (0.9, 0.2, 0.1)
    image[10:30, 50:80] = (0.1, 0.4, 0.9)
    media.save_image(path, image.astype(np.float32))
    return path


def write_bad_inputs(tmp: Path) -> dict[str, Path]:
    """Uploads the studio must refuse in one message: a corrupt PNG, a text file named .mp4, a probe
    with no finite light, and a file over the upload limit."""
    corrupt = tmp / "corrupt.png"
    corrupt.write_bytes(b"\x89PNG\r\n\x1a\n" + b"not really a picture" * 20)
    fake_video = tmp / "fake.mp4"
    fake_video.write_bytes(b"this is a text file, not a video\n" * 50)
    nan_probe = tmp / "nan.exr"
    pixels = np.full((16, 32, 3), np.nan, dtype=np.float32)
    OpenEXR.File({"type": OpenEXR.scanlineimage}, {"RGB": pixels}).write(str(nan_probe))
    big = tmp / "big.png"
    big.write_bytes(b"\0" * (UPLOAD_LIMIT_MB * 1024 * 1024 + 1))
    return {"corrupt": corrupt, "fake_video": fake_video, "nan_probe": nan_probe, "big": big}


# ---------------------------------------------------------------------------------------------
# The studio, served for a test
# ---------------------------------------------------------------------------------------------


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]


def start_studio(tmp: Path, **overrides):
    """Launch the studio in-process on the tiny model; returns (demo, local_url, share_url)."""
    from ui.server import ServerOptions, start

    options = ServerOptions(port=free_port(), model="tiny", inbrowser=False, temp_dir=tmp / "studio",
                            max_upload_mb=UPLOAD_LIMIT_MB, examples_dir=tmp / "no-examples")
    options = ServerOptions(**{**options.__dict__, **overrides})
    return start(options, block=False)


def relight_args(image: Path, **overrides) -> dict:
    """Every input of the /relight endpoint, with the defaults a user gets."""
    from gradio_client import handle_file  # here: most users of this module never talk to a studio

    args = dict(path=handle_file(str(image)), mode="Relight", probe_name="studio", probe_upload=None,
                rotation=120.0, exposure=0.0, rotate_light=False, sweep_start=0, sweep_end=360, num_seeds=1,
                frame_start=0, frame_end=0, size=64, steps=4, sampler="euler", seed=3, guidance=0.0,
                model="tiny")
    args.update(overrides)
    return args


def plain(value):
    """A streamed output as its value; skipped or cleared outputs come back as None."""
    if isinstance(value, dict) and value.get("__type__") == "update":
        return value.get("value")
    return value


def run_job(client, **args) -> list[tuple]:
    """Submit a relight job through a gradio_client `Client` and collect every streamed update."""
    job = client.submit(**args, api_name="/relight")
    updates = [tuple(plain(v) for v in update) for update in job]
    job.result()  # re-raises a server-side error
    return updates


# ---------------------------------------------------------------------------------------------
# Stand-ins for the released Cosmos tokenizer (encoder.jit / decoder.jit)
# ---------------------------------------------------------------------------------------------


class FakeCosmosEncoder(nn.Module):
    """Same I/O as the released encoder.jit: a causal 8×8×8 patch embedding, returns a tuple."""

    def __init__(self):
        super().__init__()
        self.proj = nn.Conv3d(3, 16, 8, stride=8)

    def forward(self, x: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
        padded = torch.cat([x[:, :, :1].expand(-1, -1, 7, -1, -1), x], dim=2)  # (B, 3, 8t, H, W)
        latent = self.proj(padded)  # (B, 16, t, H/8, W/8)
        return latent, latent.abs()


class FakeCosmosDecoder(nn.Module):
    """Same I/O as the released decoder.jit: 16-channel latents to 1 + 8(t-1) frames at 8× size."""

    def __init__(self):
        super().__init__()
        self.proj = nn.Conv3d(16, 3, 1)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        x = self.proj(z).repeat_interleave(8, dim=2)[:, :, 7:]  # (B, 3, T, h, w)
        return x.repeat_interleave(8, dim=3).repeat_interleave(8, dim=4)  # (B, 3, T, H, W)


# ---------------------------------------------------------------- synthetic dataset scenes

SIZE, FRAMES = 32, 9


def write_scene(root, split, index, frames=FRAMES, size=SIZE):
    """A synthetic sample in the dataset format: two lights, smooth images, a sun probe per light."""
    rng = np.random.default_rng(index)
    sample = root / split / f"scene_{index:06d}"
    y, x = np.mgrid[0:size, 0:size] / size
    albedo = np.stack([x, y, 0.5 + 0.0 * x], -1) * rng.uniform(0.5, 1.0, 3)
    for t in range(frames):
        shift = t / frames
        for light in (0, 1):
            shade = 0.3 + 0.7 * np.clip(np.cos(2 * np.pi * (x + shift + light / 2)), 0, 1)[..., None]
            write_frame(sample, f"rgb{light}", t, np.clip(albedo * shade, 0, 1))
            env = np.full((size, size, 3), 0.2, np.float32)
            env[size // 4, (size // 4 + light * size // 2 + t) % size] = 500.0
            write_frame(sample, f"env{light}", t, env)
        write_frame(sample, "albedo", t, albedo)
        write_frame(sample, "mask", t, (y > 0.2).astype(np.float32))
    write_meta(sample, {"kind": "synthetic", "frames": frames, "height": size, "width": size, "lights": 2})


# ---------------------------------------------------------------- released-checkpoint names

MINI = DiTConfig(width=64, depth=2, num_heads=2, adaln_lora_dim=16, cross_attention=True, context_dim=32)


def released_names(depth: int) -> list[str]:
    """Parameter names of a released GeneralDIT (FA-CA-MLP blocks), as stored under `net.`."""
    names = ["x_embedder.proj.1.weight", "view_embeddings.weight", "t_embedder.1.linear_1.weight",
             "t_embedder.1.linear_2.weight", "affline_norm.weight", "final_layer.linear.weight",
             "final_layer.adaLN_modulation.1.weight", "final_layer.adaLN_modulation.2.weight"]
    for i in range(depth):
        for j in range(3):
            names += [f"blocks.block{i}.blocks.{j}.adaLN_modulation.{k}.weight" for k in (1, 2)]
        for j in range(2):
            names += [f"blocks.block{i}.blocks.{j}.block.attn.{p}.weight"
                      for p in ("to_q.0", "to_q.1", "to_k.0", "to_k.1", "to_v.0", "to_out.0")]
        names += [f"blocks.block{i}.blocks.2.block.layer{k}.weight" for k in (1, 2)]
    return names


def awake(relighter):
    """Give the zero-initialised (adaLN-zero) parameters random values, so that an untrained DiT's
    output depends on its inputs (the lighting included) and conditioning tests mean something."""
    generator = torch.Generator().manual_seed(0)
    with torch.no_grad():
        for parameter in relighter.dit.parameters():
            if not parameter.any():
                parameter.copy_(0.05 * torch.randn(parameter.shape, generator=generator))
    return relighter


def make_frameless_mp4(path: Path, width: int = 16, height: int = 16) -> Path:
    """An mp4 container with a video stream and no frames at all."""
    with av.open(str(path), "w") as container:
        stream = container.add_stream("libx264", rate=24)
        stream.width, stream.height, stream.pix_fmt = width, height, "yuv420p"
        container.start_encoding()
    return path


def make_audio_only_mp4(path: Path) -> Path:
    """An mp4 with a 0.1 s silent AAC track and no video stream."""
    with av.open(str(path), "w") as container:
        sound = container.add_stream("aac", rate=44100, layout="mono")
        frame = av.AudioFrame.from_ndarray(np.zeros((1, 4410), np.float32), format="flt", layout="mono")
        frame.sample_rate = 44100
        for packet in [*sound.encode(frame), *sound.encode(None)]:
            container.mux(packet)
    return path


def terminate_when(args: list[str], ready: Callable[[], bool], what: str, settle_s: float = 0.0,
                   cwd: Path = REPO, sig: int = signal.SIGTERM, timeout_s: float = 180) -> tuple[int, str]:
    """Run `python -m relight_core ARGS`, send `sig` once `ready()` holds (and `settle_s` more
    seconds have passed); (exit code, stderr). `what` names the awaited state in a failure."""
    proc = subprocess.Popen([sys.executable, "-m", "relight_core", *map(str, args)], cwd=cwd,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + timeout_s
        while not ready():
            assert proc.poll() is None, proc.communicate()
            assert time.monotonic() < deadline, f"the command never {what}"
            time.sleep(0.02)
        time.sleep(settle_s)
        proc.send_signal(sig)
        _, err = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
    return proc.returncode, err


def main_capturing(argv: list[str]) -> tuple[int, str, str]:
    """`python -m relight_core ARGV` in this process: (exit code, stdout, stderr)."""
    from relight_core.cli import main

    stdout, stderr = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(stdout), contextlib.redirect_stderr(stderr):
        code = main(argv)
    return code, stdout.getvalue(), stderr.getvalue()


def write_pack_dataset(root, scenes=3, size=32, seed=0):
    """A train split of random scenes under two lights (frame 0, mask, probes): what `training.pack` packs."""
    rng = np.random.default_rng(seed)
    split = root / "train"
    for i in range(scenes):
        sample = split / f"scene_{i:06d}"
        for name in ("rgb0", "rgb1", "albedo"):
            write_frame(sample, name, 0, rng.random((size, size, 3)).astype(np.float32))
        write_frame(sample, "mask", 0, (rng.random((size, size)) > 0.5).astype(np.float32))
        for light in (0, 1):
            write_frame(sample, f"env{light}", 0, rng.random((size, size, 3)).astype(np.float32) * 5)
        write_meta(sample, {"kind": "synthetic", "frames": 1, "height": size, "width": size, "lights": 2})
    write_manifest(split)
    return root
