"""Malformed input, made here, through the command line and the server API (issue 8).

Every bad file or number must end with one sentence: exit code 2 and a single `error: ...` line for
the CLI, nothing written; an error event with one short sentence (naming the file) for the API,
after which the server still runs a normal job. Inputs that are odd but valid (grey, RGBA, 16-bit,
CMYK, odd sizes, a unicode path, a one-frame video) must give results.
"""

from __future__ import annotations

import io
import struct
import zlib
from pathlib import Path

import cv2
import numpy as np
import pytest
from gradio_client import handle_file
from PIL import Image

from relight_core import media
from relight_core.cli import main
from tests.factory import (make_audio_only_mp4, make_frameless_mp4, make_mp4, make_png, make_sun_probe, relight_args,
                           run_job, start_studio, write_exr)

FAST = ["--model", "tiny", "--steps", "1", "--size", "48"]


def _png_chunk(kind: bytes, data: bytes) -> bytes:
    return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))


def _png_declaring(width: int, height: int) -> bytes:
    header = struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return (b"\x89PNG\r\n\x1a\n" + _png_chunk(b"IHDR", header) + _png_chunk(b"IDAT", zlib.compress(b"\0" * 64))
            + _png_chunk(b"IEND", b""))


def _jpeg_bytes(image: Image.Image, **kwargs) -> bytes:
    buffer = io.BytesIO()
    image.save(buffer, format="JPEG", **kwargs)
    return buffer.getvalue()


def make_bad_media(d: Path) -> dict[str, Path]:
    """Input images and videos that must be refused: name → file."""
    rng = np.random.default_rng(0)
    picture = Image.fromarray((rng.random((32, 48, 3)) * 255).astype(np.uint8))
    png = io.BytesIO()
    picture.save(png, format="PNG")
    png = png.getvalue()
    jpeg = _jpeg_bytes(picture)
    webp = io.BytesIO()
    picture.save(webp, format="WEBP")
    exr = write_exr(d / "whole.exr", rng.random((32, 48, 3), dtype=np.float32)).read_bytes()
    assert cv2.imwrite(str(d / "whole.hdr"), (rng.random((32, 48, 3)) * 4).astype(np.float32))
    hdr = (d / "whole.hdr").read_bytes()
    clip = rng.random((17, 32, 48, 3), dtype=np.float32)
    media.save_video(d / "faststart.mp4", clip, 12.0)
    faststart = (d / "faststart.mp4").read_bytes()
    moov_last = make_mp4(d / "moov_last.mp4", frames=12).read_bytes()
    files = {
        "truncated.png": png[: len(png) // 2],
        "bad-crc.png": png[:40] + bytes(b ^ 0xFF for b in png[40:60]) + png[60:],
        "declares-100000x100000.png": _png_declaring(100000, 100000),
        "declares-9000x2.png": _png_declaring(9000, 2),
        "truncated.jpg": jpeg[: len(jpeg) // 3],
        "header-only.jpg": jpeg[:20],
        "truncated.webp": webp.getvalue()[: len(webp.getvalue()) // 2],
        "truncated.exr": exr[: len(exr) // 2],
        "header-only.exr": exr[:64],
        "truncated.hdr": hdr[: len(hdr) // 2],
        "no-resolution.hdr": b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n" + b"\0" * 64,
        "declares-huge.hdr": b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 100000 +X 100000\n" + b"\0" * 64,
        "text.mp4": b"this is a text file, not a video\n" * 40,
        "random.mp4": rng.integers(0, 256, 4096, dtype=np.uint8).tobytes(),
        "random.png": rng.integers(0, 256, 4096, dtype=np.uint8).tobytes(),
        "empty.png": b"",
        "truncated-faststart.mp4": faststart[: len(faststart) // 2],
        "truncated-moov-last.mp4": moov_last[: len(moov_last) // 2],
        "gif-garbage.gif": b"GIF89a" + rng.integers(0, 256, 200, dtype=np.uint8).tobytes(),
    }
    out = {}
    for name, data in files.items():
        (d / name).write_bytes(data)
        out[name] = d / name
    out["zero-frames.mp4"] = make_frameless_mp4(d / "zero-frames.mp4", 48, 32)
    out["audio-only.mp4"] = make_audio_only_mp4(d / "audio-only.mp4")
    (d / "folder.png").mkdir()
    out["folder.png"] = d / "folder.png"
    return out


def make_bad_probes(d: Path) -> dict[str, Path]:
    """Light probes that must be refused."""
    exr = make_sun_probe(d / "good-probe.exr").read_bytes()
    assert cv2.imwrite(str(d / "good-probe.hdr"), np.full((16, 32, 3), 2.0, np.float32))
    hdr = (d / "good-probe.hdr").read_bytes()
    probes = {
        "nan.exr": np.full((16, 32, 3), np.nan, np.float32),
        "inf.exr": np.full((16, 32, 3), np.inf, np.float32),
        "negative.exr": np.full((16, 32, 3), -1.0, np.float32),
        "black.exr": np.zeros((16, 32, 3), np.float32),
        "one-pixel.exr": np.ones((1, 1, 3), np.float32),
    }
    out = {}
    for name, pixels in probes.items():
        out[name] = write_exr(d / name, pixels)
    raw = {"truncated-probe.exr": exr[: len(exr) // 2], "truncated-probe.hdr": hdr[: len(hdr) // 2],
           "png-as-probe.hdr": make_png(d / "p.png").read_bytes(),
           "huge-probe.hdr": b"#?RADIANCE\nFORMAT=32-bit_rle_rgbe\n\n-Y 90000 +X 180000\n" + b"\0" * 64}
    for name, data in raw.items():
        (d / name).write_bytes(data)
        out[name] = d / name
    return out


def make_good_media(d: Path) -> dict[str, Path]:
    """Odd but valid inputs: each must give a result."""
    rng = np.random.default_rng(2)
    colour = (rng.random((23, 37, 3)) * 255).astype(np.uint8)
    Image.fromarray(colour[..., 0]).save(d / "grey.png")
    Image.fromarray(np.dstack([colour, np.full((23, 37), 128, np.uint8)])).save(d / "rgba.png")
    assert cv2.imwrite(str(d / "sixteen-bit.png"), (rng.random((23, 37, 3)) * 65535).astype(np.uint16))
    Image.fromarray(colour).convert("CMYK").save(d / "cmyk.jpg")
    Image.fromarray(colour).save(d / "odd-37x23.png")
    unicode_dir = d / "фото 写真"
    unicode_dir.mkdir()
    Image.fromarray(colour).save(unicode_dir / "снимок ✓.png")
    media.save_video(d / "one-frame.mp4", rng.random((1, 32, 48, 3), dtype=np.float32), 12.0)
    return {"grey.png": d / "grey.png", "rgba.png": d / "rgba.png", "sixteen-bit.png": d / "sixteen-bit.png",
            "cmyk.jpg": d / "cmyk.jpg", "odd-37x23.png": d / "odd-37x23.png",
            "unicode": unicode_dir / "снимок ✓.png", "one-frame.mp4": d / "one-frame.mp4"}


@pytest.fixture(scope="module")
def inputs(tmp_path_factory):
    d = tmp_path_factory.mktemp("fuzz")
    return {"bad": make_bad_media(d), "probes": make_bad_probes(d), "good": make_good_media(d),
            "png": make_png(d / "photo.png"), "probe": make_sun_probe(d / "sun.exr"),
            "mp4": make_mp4(d / "clip.mp4", frames=12), "dir": d}


NUMBER_CASES = [
    ["--rotation", "nan"], ["--rotation", "inf"], ["--rotation", "-1e300"], ["--intensity", "0"],
    ["--intensity", "-1"], ["--intensity", "inf"], ["--seed", str(2**70)], ["--seed", "-1"], ["--guidance", "nan"],
    ["--guidance", "-1"], ["--size", "0"], ["--size", "100000"], ["--steps", "0"], ["--steps", "100000"],
    ["--device", "bogus"], ["--sampler", "nonsense"],
]
VIDEO_NUMBER_CASES = [["--frames", "10:5"], ["--frames", "-3:2"], ["--frames", "40:"]]


def cli_refuses(argv: list, out: Path, capfd) -> str:
    """Run the CLI; assert exit 2, one `error:` line on stderr, no traceback, nothing written."""
    try:
        code = main([str(a) for a in argv] + ["--out", str(out)])
    except SystemExit as exit_:
        code = exit_.code
    err = [line for line in capfd.readouterr().err.splitlines() if line.strip()]
    assert code == 2, (argv, err)
    assert len(err) == 1 and err[0].startswith("error: ") and "Traceback" not in err[0], (argv, err)
    assert not out.exists() or not any(out.iterdir()), (argv, list(out.iterdir()))
    return err[0]


def test_cli_refuses_every_bad_file_and_number(inputs, tmp_path, capfd):
    cases = 0
    for name, path in inputs["bad"].items():
        line = cli_refuses(["albedo", path, *FAST], tmp_path / f"out-{cases}", capfd)
        assert path.name in line or "does not exist" in line, line
        cases += 1
    for name, path in inputs["probes"].items():
        line = cli_refuses(["relight", inputs["png"], "--probe", path, *FAST], tmp_path / f"out-{cases}", capfd)
        assert path.name in line, line
        cases += 1
    for numbers in NUMBER_CASES + VIDEO_NUMBER_CASES:
        source = inputs["mp4"] if numbers in VIDEO_NUMBER_CASES else inputs["png"]
        argv = ["relight", source, "--probe", inputs["probe"], *FAST, *numbers]
        cli_refuses(argv, tmp_path / f"out-{cases}", capfd)
        cases += 1
    assert cases >= 40


def test_cli_takes_odd_but_valid_inputs(inputs, tmp_path, capfd):
    for name, path in inputs["good"].items():  # every one decodes to frames in [0, 1] ...
        frames = media.load_media(path).frames
        assert frames.shape[1:] == ((32, 48, 3) if path.suffix == ".mp4" else (23, 37, 3)), name
        assert np.isfinite(frames).all() and 0 <= frames.min() and frames.max() <= 1 and frames.std() > 0.05, name
    for name in ("cmyk.jpg", "unicode", "one-frame.mp4"):  # ... and these go through the whole CLI
        path, out = inputs["good"][name], tmp_path / name
        assert main(["albedo", str(path), *FAST, "--out", str(out)]) == 0, capfd.readouterr().err
        written = [p.name for p in out.iterdir()]
        assert written == (["albedo.mp4"] if path.suffix == ".mp4" else ["albedo.png"]), (name, written)


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from gradio_client import Client

    tmp = tmp_path_factory.mktemp("fuzz-api")
    demo, url, _ = start_studio(tmp, max_upload_mb=50)
    client = Client(url, verbose=False)
    yield client, demo
    client.close()
    demo.close()


def api_refuses(client, name: str, **args) -> str:
    with pytest.raises(Exception) as error:
        run_job(client, **args)
    message = str(error.value)
    assert "\n" not in message.strip() and "Traceback" not in message and len(message) < 400, (name, message)
    return message


def test_api_refuses_every_bad_file_and_number_and_keeps_serving(inputs, server):
    (client, demo), good = server, inputs["png"]
    cases = 0
    from ui.layout import INPUT_TYPES

    for name, path in inputs["bad"].items():
        if path.is_dir() or path.stat().st_size == 0 or path.suffix not in INPUT_TYPES:
            continue  # a folder or an empty file cannot be uploaded; other types are refused by the upload box
        whole_clip = dict(frame_end=16) if path.suffix == ".mp4" else {}  # a truncated clip's head is fine
        message = api_refuses(client, name, **relight_args(path, steps=1, **whole_clip))
        assert path.name in message, (name, message)
        cases += 1
    for name, path in inputs["probes"].items():
        message = api_refuses(client, name, **relight_args(good, steps=1, probe_upload=handle_file(str(path))))
        assert path.name in message, (name, message)
        cases += 1
    for overrides in [dict(rotate_light=True, sweep_start=1e308), dict(rotate_light=True, sweep_end=-1e308),
                      dict(seed=2**70), dict(seed=-1), dict(path=handle_file(str(inputs["mp4"])), frame_start=3,
                                                             frame_end=1),
                      dict(path=handle_file(str(inputs["mp4"])), frame_start=0, frame_end=40),
                      dict(probe_name="no-such-probe"), dict(mode="Relight", probe_name=None),
                      # refused by the components' own ranges and choices
                      dict(steps=0), dict(steps=100000), dict(guidance=-1.0), dict(exposure=100.0),
                      dict(size=100000), dict(mode="Random illumination", num_seeds=1000),
                      dict(sampler="nonsense")]:
        api_refuses(client, str(overrides), **relight_args(good, **{"steps": 1, **overrides}))
        cases += 1
    assert cases >= 40
    # Nothing half-written is left behind: every refused job's folder is gone from the studio's work folder.
    jobs = Path(demo.studio_root) / "work" / "jobs"
    assert jobs.is_dir() and not any(jobs.iterdir()), list(jobs.iterdir())
    assert "Done" in run_job(client, **relight_args(good, steps=1))[-1][0]
