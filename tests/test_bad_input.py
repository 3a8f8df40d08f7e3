"""Bad input on the command line: one line on stderr (`error: ...`), exit code 2, nothing written.

Real files made here: a faststart MP4 cut in half (PyAV), a 1-frame MP4, a Radiance .hdr cut short
(OpenCV), plus the absurd numbers of issue 8 (sizes no machine holds, seeds past 2⁶³−1, NaN/Inf
angles, zero intensity, reversed seed ranges, missing or unknown devices).
"""

from __future__ import annotations

import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import cv2
import numpy as np
import pytest
import torch

from relight_core import lighting, media
from relight_core.arguments import MAX_ROTATION_DEG, MAX_SEED
from relight_core.cli import main
from relight_core.errors import InputError
from tests.factory import make_png, make_sun_probe, terminate_when

ROOT = Path(__file__).resolve().parent.parent
FAST = ["--model", "tiny", "--steps", "1", "--size", "48"]


@pytest.fixture(scope="module")
def files(tmp_path_factory):
    d = tmp_path_factory.mktemp("bad-input")
    clip = np.random.default_rng(0).random((17, 32, 48, 3), dtype=np.float32)
    whole = d / "whole.mp4"
    media.save_video(whole, clip, 12.0)  # faststart: the frame index is at the front
    data = whole.read_bytes()
    (d / "half.mp4").write_bytes(data[: len(data) // 2])
    media.save_video(d / "single.mp4", clip[:1], 12.0)
    env = np.random.default_rng(1).random((32, 64, 3), dtype=np.float32) * 4
    assert cv2.imwrite(str(d / "whole.hdr"), env[..., ::-1])
    data = (d / "whole.hdr").read_bytes()
    (d / "cut.hdr").write_bytes(data[: len(data) // 2])
    return {"png": make_png(d / "photo.png"), "probe": make_sun_probe(d / "sun.exr"), "whole": whole,
            "half": d / "half.mp4", "single": d / "single.mp4", "hdr": d / "whole.hdr", "cut_hdr": d / "cut.hdr"}


def run_cli(argv: list[str], capfd) -> tuple[int, list[str]]:
    """Run the CLI in-process; (exit code, non-empty stderr lines) — file-descriptor level, so lines that
    C libraries print straight to fd 2 count too."""
    try:
        code = main([str(a) for a in argv])
    except SystemExit as exit_:
        code = exit_.code
    err = capfd.readouterr().err
    return code, [line for line in err.splitlines() if line.strip()]


def assert_one_sentence(code: int, lines: list[str], *fragments: str) -> str:
    assert code == 2, lines
    assert len(lines) == 1, lines  # no usage block, no OpenCV log line, no traceback
    line = lines[0]
    assert line.startswith("error: ") and line.endswith("."), line
    for fragment in fragments:
        assert fragment in line, (fragment, line)
    return line


# -- numbers, seeds and argparse errors: refused before anything is loaded ----------------------

RELIGHT = ["relight", "{png}", "--probe", "{probe}"]
ARG_CASES = [
    (RELIGHT + ["--rotation", "nan"], "rotation"),
    (RELIGHT + ["--rotation", "inf"], "rotation"),
    (RELIGHT + ["--rotation", "-inf"], "rotation"),
    (RELIGHT + ["--rotation", "1e300"], "rotation"),
    (RELIGHT + ["--intensity", "0"], "intensity"),
    (RELIGHT + ["--intensity", "-2"], "intensity"),
    (RELIGHT + ["--intensity", "nan"], "intensity"),
    (RELIGHT + ["--intensity", "1e300"], "intensity"),
    (RELIGHT + ["--guidance", "nan"], "guidance"),
    (RELIGHT + ["--seed", "1180591620717411303424"], "seed"),
    (RELIGHT + ["--seed", str(MAX_SEED + 1)], "seed"),
    (RELIGHT + ["--seed", "-1"], "seed"),
    (RELIGHT + ["--seed", "abc"], "seed"),
    (RELIGHT + ["--size", "0"], "--size"),
    (RELIGHT + ["--size", "big"], "--size"),
    (RELIGHT + ["--frames", "a:b"], "frame range"),
    (RELIGHT + ["--frames", "10:5"], "the frame range '10:5' holds no frame; write START:END with 0 ≤ START < END"),
    (RELIGHT + ["--frames=-3:2"], "the frame range '-3:2' holds no frame"),
    (RELIGHT + ["--bogus-option"], "unrecognized"),
    (["relight", "{png}"], "required"),
    (["augment", "{png}", "--seeds", "5-1"], "reversed"),
    (["augment", "{png}", "--seeds", "0-99999999999999"], "256"),
    (["augment", "{png}", "--seeds", "-3"], "out of range"),
    (["augment", "{png}", "--seeds", "9223372036854775806-9223372036854775808"], "out of range"),
    (["augment", "{png}", "--seeds", "x-y"], "seed list"),
    (["no-such-command"], "invalid choice"),
]


@pytest.mark.parametrize("argv, fragment", ARG_CASES, ids=[" ".join(a[4:] or a[:2]) for a, _ in ARG_CASES])
def test_bad_arguments_are_one_line_and_exit_2(argv, fragment, files, tmp_path, capfd):
    out = tmp_path / "out"
    argv = [a.format(png=files["png"], probe=files["probe"]) for a in argv]
    if argv[0] != "no-such-command" and "--out" not in argv and argv != ["relight", str(files["png"])]:
        argv += ["--out", str(out), *FAST]
    code, lines = run_cli(argv, capfd)
    line = assert_one_sentence(code, lines, fragment)
    assert "usage:" not in line
    assert not out.exists()


def test_the_largest_seed_is_accepted(files, tmp_path, capfd):
    code, _ = run_cli(["albedo", files["png"], "--seed", str(MAX_SEED), "--out", tmp_path, *FAST], capfd)
    assert code == 0 and (tmp_path / "albedo.png").is_file()


def test_app_argument_errors_are_one_line(capsys):
    from app import parse_args

    for argv, fragment in [(["--port", "99999"], "port"), (["--auth", "nopassword"], "USER:PASS"),
                           (["--max-upload-mb", "-1"], "upload"), (["--nonsense"], "unrecognized")]:
        with pytest.raises(SystemExit) as exit_:
            parse_args(argv)
        lines = [line for line in capsys.readouterr().err.splitlines() if line.strip()]
        assert exit_.value.code == 2 and len(lines) == 1 and fragment in lines[0], lines


# -- sizes, devices, damaged files: refused with one sentence, nothing written ------------------

@pytest.mark.parametrize("size", ["20000", "100000"])
def test_a_size_the_machine_cannot_hold_is_refused_before_allocating(size, files, tmp_path, capfd, monkeypatch):
    # A machine with 16 GB free (whatever this one has): 20000² needs far more even for the tiny model.
    monkeypatch.setattr("relight_core.costs.free_memory", lambda device: (16 << 30, None))
    out = tmp_path / "out"
    started = time.monotonic()
    code, lines = run_cli(["relight", files["png"], "--probe", files["probe"], "--out", out, "--model", "tiny",
                           "--steps", "1", "--size", size], capfd)
    line = assert_one_sentence(code, lines, "memory", "GB")
    # It names the limit: a long side that fits, smaller than the one asked for.
    fits = int(re.search(r"at most about (\d+) pixels", line).group(1))
    assert 16 <= fits < int(size)
    assert time.monotonic() - started < 60  # refused from an estimate, not after trying
    assert not out.exists() or not any(out.iterdir())


def test_memory_estimate_grows_with_size_and_frames():
    from relight_core.pipeline import Relighter

    relighter = Relighter.load("tiny", device="cpu")
    small, big = sum(relighter.memory_estimate(1, 64, 64)), sum(relighter.memory_estimate(1, 640, 640))
    assert 50 < big / small < 200  # roughly linear in pixels
    assert sum(relighter.memory_estimate(40, 64, 64)) > 10 * small
    relighter.check_memory(1, 64, 64)  # a normal request passes
    with pytest.raises(InputError, match="fewer frames"):
        relighter.check_memory(10**9, 64, 64)


@pytest.mark.parametrize("device, fragment", [("bogus", "not a device"), ("cuda:x", "not a device"),
                                              ("cuda", "no usable CUDA GPU")])
def test_a_missing_or_unknown_device_is_named(device, fragment, files, tmp_path, capfd):
    if device == "cuda" and torch.cuda.is_available():
        pytest.skip("this machine has a CUDA GPU")
    code, lines = run_cli(["albedo", files["png"], "--device", device, "--out", tmp_path / "out", *FAST], capfd)
    line = assert_one_sentence(code, lines, fragment)
    assert "safetensors" not in line and "re-download" not in line


def test_a_truncated_video_says_how_many_frames_could_be_read(files, tmp_path, capfd):
    with pytest.raises(InputError) as info:
        media.load_media(files["half"])
    match = re.search(r"only (\d+) of its 17 frames could be read", str(info.value))
    assert match and 0 < int(match.group(1)) < 17, str(info.value)
    assert media.load_media(files["whole"]).frames.shape[0] == 17
    # The readable head of a truncated file is still usable on its own.
    assert media.load_video(files["half"], end=int(match.group(1))).frames.shape[0] == int(match.group(1))
    out = tmp_path / "out"
    code, lines = run_cli(["albedo", files["half"], "--out", out, *FAST], capfd)
    assert_one_sentence(code, lines, "half.mp4", "of its 17 frames")
    assert not out.exists() or not any(out.iterdir())


def test_a_truncated_hdr_is_one_line_without_opencv_noise(files, tmp_path, capfd):
    assert lighting.load_probe(files["hdr"]).shape == (32, 64, 3)
    code, lines = run_cli(["relight", files["png"], "--probe", files["cut_hdr"], "--out", tmp_path / "o", *FAST],
                          capfd)
    assert_one_sentence(code, lines, "cut.hdr")
    with pytest.raises(InputError):
        lighting.load_probe(files["cut_hdr"])
    assert capfd.readouterr().err == ""  # OpenCV's "[ERROR:0@...] global loadsave.cpp" line is gone


def test_angles_and_intensity_are_checked_below_the_command_line():
    for sweep in [(0.0, 1e308), (-1e308, 0.0), (0.0, float("nan"))]:
        with pytest.raises(InputError, match="sweep"):
            lighting.frame_rotations(5, 0.0, True, sweep)
    with pytest.raises(InputError, match="rotation"):
        lighting.frame_rotations(1, float("inf"))
    assert lighting.frame_rotations(3, MAX_ROTATION_DEG, True, (-MAX_ROTATION_DEG, 0.0))[0] == 0.0
    with pytest.raises(InputError, match="intensity"):
        lighting.load_probe(ROOT / "envmaps" / "sunset.exr", intensity=0.0)


def test_pipeline_refuses_out_of_range_seeds_and_accepts_the_largest():
    from relight_core.pipeline import Relighter, RelightRequest

    relighter = Relighter.load("tiny", device="cpu")
    frames = np.full((1, 16, 16, 3), 0.5, np.float32)
    for seed in (-1, MAX_SEED + 1, 2**70):
        with pytest.raises(InputError, match="seed"):
            relighter.relight(RelightRequest(frames, mode="albedo", seed=seed, steps=1))
    a = relighter.relight(RelightRequest(frames, mode="albedo", seed=MAX_SEED, steps=1)).albedo
    b = relighter.relight(RelightRequest(frames, mode="albedo", seed=MAX_SEED, steps=1)).albedo
    np.testing.assert_array_equal(a, b)


# -- files written: normal permissions ----------------------------------------------------------

def test_written_files_are_0644_not_private(files, tmp_path, capfd):
    previous = os.umask(0o022)
    try:
        media.save_image(tmp_path / "a.png", np.zeros((8, 8, 3), np.float32))
        media.save_exr(tmp_path / "a.exr", np.zeros((8, 8, 3), np.float32))
        media.save_video(tmp_path / "a.mp4", np.zeros((2, 16, 16, 3), np.float32), 12.0)
        code, _ = run_cli(["relight", files["png"], "--probe", files["probe"], "--out", tmp_path / "out", *FAST],
                          capfd)
    finally:
        os.umask(previous)
    assert code == 0
    written = [tmp_path / n for n in ("a.png", "a.exr", "a.mp4")] + list((tmp_path / "out").iterdir())
    assert len(written) == 5
    for path in written:
        assert path.stat().st_mode & 0o777 == 0o644, (path, oct(path.stat().st_mode))


# -- SIGTERM: cleaned up like Ctrl+C ------------------------------------------------------------

def test_sigterm_leaves_no_partial_folder(files, tmp_path):
    out = tmp_path / "out"
    code, err = terminate_when(  # staged outputs: the job is sampling
        ["relight", files["png"], "--probe", files["probe"], "--out", out, "--model", "tiny", "--steps", "1000",
         "--size", "64"], lambda: bool(list(out.glob(".partial-*"))), "started sampling")
    assert code == 128 + signal.SIGTERM, err
    assert "stopped." in err and "Traceback" not in err
    assert list(out.iterdir()) == []


# A SIGTERM raised while Thread.start() waits for the sampler thread (or while the caller's loop
# body runs) left a daemon worker inside torch at exit: "terminate called without an active
# exception", exit -6 (seen once in CI). The signal is delivered at exactly those points here.
_SIGNAL_AT = """
import os, signal, sys, threading
from relight_core.cli import main
where = sys.argv[1]
if where == "start":
    start = threading.Thread.start
    def start_then_signal(self):
        start(self)
        if self.name == "relight-sampler":
            os.kill(os.getpid(), signal.SIGTERM)  # raised here, as start() returns
    threading.Thread.start = start_then_signal
else:
    import tqdm
    update, calls = tqdm.tqdm.update, []
    def update_then_signal(self, n=1):
        calls.append(n)
        if len(calls) == 2:
            os.kill(os.getpid(), signal.SIGTERM)  # raised in the CLI's loop body, the generator suspended
        return update(self, n)
    tqdm.tqdm.update = update_then_signal
code = main(sys.argv[2:])
assert not [t for t in threading.enumerate() if t.name == "relight-sampler"], "a sampler thread outlived main()"
sys.exit(code)
"""


@pytest.mark.parametrize("where", ["start", "loop"])
def test_sigterm_as_the_sampler_thread_starts_or_between_steps_exits_cleanly(files, tmp_path, where):
    out = tmp_path / "out"
    proc = subprocess.run([sys.executable, "-c", _SIGNAL_AT, where, "relight", str(files["png"]), "--probe",
                           str(files["probe"]), "--out", str(out), "--model", "tiny", "--steps", "1000",
                           "--size", "64"], cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 128 + signal.SIGTERM, proc.stderr
    assert "stopped." in proc.stderr and "terminate called" not in proc.stderr and "Traceback" not in proc.stderr
    assert list(out.iterdir()) == []
