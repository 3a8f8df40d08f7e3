"""relight_core/outputs.py: what each mode writes, and the files (PNG, MP4 with audio, linear EXR)."""

from __future__ import annotations

import os
from types import SimpleNamespace

import av
import numpy as np

from relight_core import media
from relight_core.outputs import MODE_OUTPUTS, result_clips, write_outputs
from relight_core.requests import MODES
from tests.factory import make_mp4


def _clip(t: int, value: float, h: int = 16, w: int = 24) -> np.ndarray:
    frames = np.full((t, h, w, 3), value, np.float32)
    frames[:, :, : w // 2] = np.linspace(0.1, 0.9, t)[:, None, None, None]  # each frame its own
    return frames


def test_every_mode_has_its_outputs_and_render_does_not_write_its_own_input():
    assert set(MODE_OUTPUTS) == set(MODES)
    assert MODE_OUTPUTS["albedo"] == ("albedo",) and MODE_OUTPUTS["render"] == ("relit",)
    assert MODE_OUTPUTS["relight"] == ("relit", "albedo")


def test_result_clips_picks_the_modes_clips_and_upsamples_to_the_full_frames():
    working = _clip(1, 0.5)
    result = SimpleNamespace(relit=_clip(1, 0.25), albedo=_clip(1, 0.75))
    assert list(result_clips(result, "albedo", working)) == ["albedo"]
    full = media.resize_frames(working, 48)  # 48×32
    clips = result_clips(result, "relight", working, full)
    assert [c.shape for c in clips.values()] == [full.shape, full.shape]


def test_an_image_gets_pngs_and_a_linear_exr_of_the_named_clips(tmp_path):
    clips = {"relit": _clip(1, 0.5), "albedo": _clip(1, 0.25)}
    files = write_outputs(clips, tmp_path, video=False, suffix="-seed3", stills=True, linear=("relit",))
    assert {k: v.name for k, v in files.items()} == {
        "relit": "relit-seed3.png", "relit_still": "relit-seed3.png", "relit_linear": "relit-seed3-linear.exr",
        "albedo": "albedo-seed3.png", "albedo_still": "albedo-seed3.png"}
    exr = media.read_hdr(files["relit_linear"])
    np.testing.assert_allclose(exr, media.srgb_to_linear(media.load_media(files["relit"]).frames[0]), atol=6e-3)
    assert oct(os.stat(files["relit"]).st_mode & 0o777) == oct(0o666 & ~_umask())


def test_a_video_gets_mp4s_with_the_sources_audio_and_its_middle_frame_as_a_still(tmp_path):
    source = media.load_media(make_mp4(tmp_path / "in.mp4", frames=5, width=24, height=16, audio=True))
    clips = {"relit": _clip(5, 0.5)}
    files = write_outputs(clips, tmp_path / "out", True, source.fps, source.audio_path, source.audio_start,
                          prefix="seed0001_", stills=True, linear=("relit",))
    assert {k: v.name for k, v in files.items()} == {"relit": "seed0001_relit.mp4",
                                                       "relit_still": "seed0001_relit.png"}
    with av.open(str(files["relit"])) as container:
        assert len(container.streams.audio) == 1
        assert sum(1 for _ in container.decode(video=0)) == 5
    still = media.load_media(files["relit_still"]).frames[0]
    assert abs(float(still[:, :6].mean()) - 0.5) < 0.02  # frame 2 of 5: the middle one
    assert not list((tmp_path / "out").glob("*.partial"))


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_a_video_written_from_its_file_gives_the_whole_clips_frames_and_middle_still(tmp_path):
    # write_outputs(full=FullVideo) brings a video's results to its own size 16 frames at a time from the file; its
    # still is the middle frame caught on the way. Both must be what upsampling the whole clip at once gives.
    from relight_core.outputs import FullVideo

    clip = make_mp4(tmp_path / "clip.mp4", frames=20, width=48, height=32)
    full = media.load_video(clip).frames
    working = media.resize_frames(full, 24)
    relit = np.clip(working * np.linspace(0.5, 1.5, 20, dtype=np.float32)[:, None, None, None], 0, 1)
    whole = result_clips(SimpleNamespace(relit=relit), "render", working, full)["relit"]
    files = write_outputs({"relit": relit}, tmp_path / "out", True, 12.0, stills=True, full=FullVideo(str(clip)),
                          working=working)
    still = media.load_media(files["relit_still"]).frames[0]
    media.save_image(tmp_path / "expected.png", whole[10])
    assert np.array_equal(still, media.load_media(tmp_path / "expected.png").frames[0])
    assert media.probe_video(files["relit"]).num_frames == 20
