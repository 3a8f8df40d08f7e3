"""Media I/O on real files written by the tests: images, videos with and without audio, bad input."""

import io
import os
import struct
import zlib
from fractions import Fraction

import av
import numpy as np
import OpenEXR
import pytest
from PIL import Image

from relight_core.errors import InputError
from relight_core.media import (
    Media,
    iter_video,
    load_image,
    load_media,
    load_video,
    media_kind,
    probe_video,
    linear_to_srgb,
    read_hdr,
    resize_frames,
    save_exr,
    save_image,
    save_video,
    srgb_to_linear,
)
from tests.factory import make_audio_only_mp4, make_frameless_mp4


def gradient(h, w, t=0) -> np.ndarray:
    """A smooth uint8 test picture whose red channel encodes the frame index t."""
    y, x = np.mgrid[0:h, 0:w]
    rgb = np.stack([np.full((h, w), 20 * t + 10), 255 * x / max(w - 1, 1), 255 * y / max(h - 1, 1)], axis=-1)
    return rgb.astype(np.uint8)


def write_mp4(path, num_frames=9, fps=Fraction(24), size=(32, 48), audio=False, rotation=None) -> None:
    h, w = size
    with av.open(str(path), "w", format="mp4") as out:
        video = out.add_stream("libx264", rate=fps)
        video.width, video.height, video.pix_fmt = w, h, "yuv420p"
        if rotation is not None:
            video.set_display_rotation(rotation)
        if audio:
            sound = out.add_stream("aac", rate=44100, layout="mono")
            t = np.arange(int(44100 * num_frames / fps)) / 44100
            frame = av.AudioFrame.from_ndarray((0.3 * np.sin(2 * np.pi * 440 * t)).astype(np.float32)[None], format="flt", layout="mono")
            frame.sample_rate = 44100
            for packet in sound.encode(frame):
                out.mux(packet)
            for packet in sound.encode(None):
                out.mux(packet)
        for i in range(num_frames):
            frame = av.VideoFrame.from_ndarray(gradient(h, w, i), format="rgb24")
            frame.pts = i
            for packet in video.encode(frame):
                out.mux(packet)
        for packet in video.encode(None):
            out.mux(packet)


def audio_seconds(path) -> float | None:
    with av.open(str(path)) as container:
        if not container.streams.audio:
            return None
        stream = container.streams.audio[0]
        return float(stream.duration * stream.time_base)


# ---------------------------------------------------------------------------------------------
# Images
# ---------------------------------------------------------------------------------------------


def test_png_jpeg_webp(tmp_path):
    rgb = gradient(20, 30)
    Image.fromarray(rgb).save(tmp_path / "a.png")
    Image.fromarray(rgb).save(tmp_path / "a.jpg", quality=95)
    Image.fromarray(rgb).save(tmp_path / "a.webp", lossless=True)
    for name, tolerance in [("a.png", 0.0), ("a.jpg", 0.05), ("a.webp", 0.0)]:
        media = load_media(tmp_path / name)
        assert isinstance(media, Media) and not media.is_video and media.fps is None and media.audio_path is None
        assert media.frames.shape == (1, 20, 30, 3) and media.frames.dtype == np.float32
        assert np.abs(media.frames[0] - rgb / 255.0).mean() <= tolerance + 1e-6, name


def test_detection_is_by_content_not_extension(tmp_path):
    Image.fromarray(gradient(8, 12)).save(tmp_path / "picture.mp4", format="PNG")
    assert load_media(tmp_path / "picture.mp4").frames.shape == (1, 8, 12, 3)
    write_mp4(tmp_path / "clip.png")
    assert load_media(tmp_path / "clip.png").is_video


def flat_frames(count, height=12, width=20):
    """`count` frames of one flat colour each, far apart: exact in a GIF's palette and in any codec."""
    colours = [(230, 20, 20), (20, 200, 40), (30, 40, 220), (240, 240, 10), (10, 10, 10)]
    return [np.full((height, width, 3), colours[i % len(colours)], np.uint8) for i in range(count)]


@pytest.mark.parametrize("suffix,options", [(".gif", {}), (".png", {}), (".webp", {"lossless": True})])
def test_an_animated_gif_png_or_webp_is_a_clip_with_its_frames_and_their_rate(tmp_path, suffix, options):
    frames = flat_frames(5)
    path = tmp_path / f"anim{suffix}"
    images = [Image.fromarray(f) for f in frames]
    images[0].save(path, save_all=True, append_images=images[1:], duration=[80, 80, 160, 80, 80], loop=0, **options)
    assert media_kind(path) == "video"
    info = probe_video(path)
    assert (info.num_frames, info.width, info.height, info.has_audio) == (5, 20, 12, False)
    assert info.fps == pytest.approx(12.5)  # 1000 / the median delay of 80 ms
    clip = load_media(path)
    assert clip.is_video and clip.fps == pytest.approx(12.5) and clip.audio_path is None
    np.testing.assert_allclose(clip.frames, np.stack(frames) / 255.0, atol=1.5 / 255)
    part = load_video(path, start=2, end=4)  # frames 2 and 3; frame 2 starts at 160 ms
    np.testing.assert_allclose(part.frames, np.stack(frames[2:4]) / 255.0, atol=1.5 / 255)
    assert part.audio_start == pytest.approx(0.16)
    blocks = list(iter_video(path, 1, 5, 3))
    assert [b.shape[0] for b in blocks] == [3, 1]
    np.testing.assert_allclose(np.concatenate(blocks), clip.frames[1:5], atol=1e-6)
    single = tmp_path / f"still{suffix}"
    images[0].save(single, **options)  # one frame: an image, as before
    assert media_kind(single) == "image" and load_media(single).frames.shape == (1, 12, 20, 3)


def test_a_cameras_multi_picture_jpeg_stays_a_photo(tmp_path):
    first, second = (Image.fromarray(f) for f in flat_frames(2))
    first.save(tmp_path / "camera.jpg", format="MPO", save_all=True, append_images=[second])
    assert Image.open(tmp_path / "camera.jpg").n_frames == 2  # two pictures, as a stereo camera writes
    assert media_kind(tmp_path / "camera.jpg") == "image"
    picture = load_media(tmp_path / "camera.jpg")
    assert picture.frames.shape == (1, 12, 20, 3)
    np.testing.assert_allclose(picture.frames[0], np.asarray(first) / 255.0, atol=0.03)


def test_an_animations_transparency_goes_over_white_and_damage_is_one_sentence(tmp_path):
    rgba = np.zeros((8, 8, 4), np.uint8)
    rgba[..., 0], rgba[:4, :, 3], rgba[4:, :, 3] = 200, 255, 0  # red on top, transparent below
    second = rgba.copy()
    second[..., :3] = (0, 0, 200)
    path = tmp_path / "alpha.png"
    Image.fromarray(rgba).save(path, save_all=True, append_images=[Image.fromarray(second)], duration=50,
                               disposal=1)
    clip = load_media(path)
    assert clip.frames.shape == (2, 8, 8, 3)
    np.testing.assert_allclose(clip.frames[0, 0, 0], [200 / 255, 0, 0], atol=1e-6)
    np.testing.assert_allclose(clip.frames[:, 7, 7], 1.0, atol=1e-6)  # transparent: white
    np.testing.assert_allclose(clip.frames[1, 0, 0], [0, 0, 200 / 255], atol=1e-6)
    assert clip.fps == pytest.approx(20.0)
    data = path.read_bytes()
    (tmp_path / "cut.png").write_bytes(data[: int(len(data) * 0.7)])
    with pytest.raises(InputError) as info:
        load_media(tmp_path / "cut.png")
    assert "damaged or truncated" in str(info.value) and "cut.png" in str(info.value)


def test_jpeg_exif_orientation(tmp_path):
    rgb = np.zeros((20, 40, 3), np.uint8)
    rgb[:5, :5] = 255  # top-left marker
    exif = Image.Exif()
    exif[0x0112] = 6  # stored image must be turned 90° clockwise for display
    Image.fromarray(rgb).save(tmp_path / "o.jpg", exif=exif, quality=95)
    frame = load_image(tmp_path / "o.jpg")[0]
    assert frame.shape == (40, 20, 3)
    assert frame[:5, -5:].mean() > 0.9 and frame[:5, :5].mean() < 0.1  # marker now top-right


def test_alpha_greyscale_and_16_bit(tmp_path):
    rgba = np.zeros((4, 6, 4), np.uint8)
    rgba[..., 0] = 255
    rgba[:, :3, 3] = 255  # left half opaque red, right half transparent
    Image.fromarray(rgba, "RGBA").save(tmp_path / "alpha.png")
    frame = load_image(tmp_path / "alpha.png")[0]
    assert np.allclose(frame[:, 0], [1, 0, 0]) and np.allclose(frame[:, -1], [1, 1, 1])  # over white

    Image.fromarray(np.full((4, 6), 128, np.uint8), "L").save(tmp_path / "grey.png")
    assert np.allclose(load_image(tmp_path / "grey.png"), 128 / 255)

    grey16 = np.full((4, 6), 1000, np.uint16)  # not representable in 8 bits
    Image.fromarray(grey16).save(tmp_path / "grey16.png")
    assert np.allclose(load_image(tmp_path / "grey16.png"), 1000 / 65535, atol=1e-6)

    import cv2

    rgb16 = np.zeros((4, 6, 3), np.uint16)
    rgb16[..., 0] = 1000  # red, written as BGR by OpenCV
    cv2.imwrite(str(tmp_path / "rgb16.png"), rgb16[..., ::-1])
    frame = load_image(tmp_path / "rgb16.png")[0]
    assert np.allclose(frame[..., 0], 1000 / 65535, atol=1e-6) and frame[..., 2].max() == 0


def test_exr_image_is_display_transformed(tmp_path):
    linear = np.array([[[0.0, 0.5, 4.0]]], np.float32).repeat(2, 0).repeat(2, 1)
    header = {"compression": OpenEXR.ZIP_COMPRESSION, "type": OpenEXR.scanlineimage}
    OpenEXR.File(header, {"RGB": linear}).write(str(tmp_path / "lin.exr"))
    frame = load_media(tmp_path / "lin.exr").frames[0, 0, 0]
    assert frame == pytest.approx([0.0, 1.055 * 0.5 ** (1 / 2.4) - 0.055, 1.0], abs=1e-6)


def test_save_image_and_exr_round_trip(tmp_path):
    rgb = gradient(10, 14) / 255.0
    save_image(tmp_path / "out" / "x.png", rgb)
    assert np.allclose(load_image(tmp_path / "out" / "x.png")[0], rgb, atol=0.5 / 255 + 1e-6)
    linear = np.random.default_rng(0).uniform(0, 30, (6, 8, 3)).astype(np.float32)
    save_exr(tmp_path / "x.exr", linear)
    with OpenEXR.File(str(tmp_path / "x.exr")) as f:
        assert np.array_equal(f.channels()["RGB"].pixels, linear)
    save_exr(tmp_path / "h.exr", linear, half=True)
    with OpenEXR.File(str(tmp_path / "h.exr")) as f:
        pixels = f.channels()["RGB"].pixels
        assert pixels.dtype == np.float16 and np.allclose(pixels, linear, rtol=1e-3)
    assert sorted(os.listdir(tmp_path)) == ["h.exr", "out", "x.exr"]  # no temporary files left


def test_the_one_hdr_reader_serves_pictures_probes_and_the_dataset(tmp_path):
    """`read_hdr` reads EXR (any channel pixel types, grey) and Radiance alike; each caller keeps its own
    size limit, checked from the header before any pixel is decoded, and names the file its own way."""
    import cv2

    from relight_core import lighting
    from relight_core.data import files

    mixed = {"R": np.full((4, 6), 1.5, np.float32), "G": np.full((4, 6), 2.0, np.float16),
             "B": np.full((4, 6), 3.0, np.float32)}                 # half and float planes in one file
    OpenEXR.File({"type": OpenEXR.scanlineimage}, mixed).write(str(tmp_path / "mixed.exr"))
    expected = np.broadcast_to(np.float32([1.5, 2.0, 3.0]), (4, 6, 3))
    np.testing.assert_array_equal(read_hdr(tmp_path / "mixed.exr"), expected)
    np.testing.assert_array_equal(files.read_exr(tmp_path / "mixed.exr"), expected)
    np.testing.assert_array_equal(lighting.load_probe(tmp_path / "mixed.exr").numpy(), expected)
    cv2.imwrite(str(tmp_path / "p.hdr"), np.full((4, 6, 3), 0.25, np.float32))
    assert read_hdr(tmp_path / "p.hdr").shape == (4, 6, 3) and np.allclose(read_hdr(tmp_path / "p.hdr"), 0.25)
    seen = []

    def refuse(width, height):
        seen.append((width, height))
        raise InputError("too big.")

    for name in ("mixed.exr", "p.hdr"):
        with pytest.raises(InputError, match="too big"):
            read_hdr(tmp_path / name, check_size=refuse)
    assert seen == [(6, 4), (6, 4)]
    (tmp_path / "note.exr").write_text("not an image")
    with pytest.raises(InputError, match="^The light probe note.exr is not an OpenEXR"):
        lighting.load_probe(tmp_path / "note.exr")
    with pytest.raises(InputError, match="^note.exr is not a supported image"):
        load_image(tmp_path / "note.exr")


# ---------------------------------------------------------------------------------------------
# Videos
# ---------------------------------------------------------------------------------------------


def test_video_load_and_probe(tmp_path):
    write_mp4(tmp_path / "v.mp4", num_frames=9, fps=Fraction(30000, 1001), audio=True)
    info = probe_video(tmp_path / "v.mp4")
    assert (info.num_frames, info.width, info.height, info.has_audio) == (9, 48, 32, True)
    assert info.fps == pytest.approx(29.97, abs=1e-2)
    media = load_media(tmp_path / "v.mp4")
    assert media.is_video and media.frames.shape == (9, 32, 48, 3) and media.frames.dtype == np.float32
    assert media.audio_path == str(tmp_path / "v.mp4") and media.audio_start == pytest.approx(0.0, abs=1e-3)
    red = media.frames[:, 16, 24, 0] * 255  # encodes the frame index (yuv420p costs a few levels)
    assert np.allclose(red, 20 * np.arange(9) + 10, atol=8)


def test_video_range_and_size(tmp_path):
    write_mp4(tmp_path / "v.mp4", num_frames=9, fps=Fraction(25))
    media = load_video(tmp_path / "v.mp4", start=2, end=7, max_frames=3, size=64)
    assert media.frames.shape == (3, 48, 64, 3)  # 32×48 → long side 64 → 42.7 → 48
    assert np.allclose(media.frames[:, 24, 32, 0] * 255, [50, 70, 90], atol=8)
    assert media.audio_path is None and media.audio_start == pytest.approx(2 / 25, abs=1e-3)


def test_video_rotation_metadata(tmp_path):
    write_mp4(tmp_path / "r.mp4", num_frames=1, size=(32, 64), rotation=90)
    assert (probe_video(tmp_path / "r.mp4").width, probe_video(tmp_path / "r.mp4").height) == (32, 64)
    frame = load_media(tmp_path / "r.mp4").frames[0]
    assert frame.shape == (64, 32, 3)
    # 90° counter-clockwise: the stored top row (blue = 0) becomes the left column.
    assert frame[:, 0, 2].max() < 0.1 and frame[:, -1, 2].min() > 0.9


def test_iter_video_gives_load_videos_frames_a_block_at_a_time_rotation_and_range_included(tmp_path):
    # What writes a video's results at full size (outputs.FullVideo) reads its frames with iter_video: they must be
    # load_video's frames, in order, upright (a phone's portrait clip stores them turned), over the same range.
    from relight_core.media import iter_video

    write_mp4(tmp_path / "r.mp4", num_frames=9, size=(32, 64), rotation=90)
    whole = load_media(tmp_path / "r.mp4").frames
    blocks = list(iter_video(tmp_path / "r.mp4", block=4))
    assert [b.shape for b in blocks] == [(4, 64, 32, 3), (4, 64, 32, 3), (1, 64, 32, 3)]
    assert np.array_equal(np.concatenate(blocks), whole)
    assert np.array_equal(np.concatenate(list(iter_video(tmp_path / "r.mp4", 2, 7, 16))), whole[2:7])


@pytest.mark.parametrize("odd", [False, True])
def test_save_video_round_trip(tmp_path, odd):
    write_mp4(tmp_path / "src.mp4", num_frames=9, fps=Fraction(24), audio=True)
    source = load_media(tmp_path / "src.mp4")
    frames = source.frames[:, :31, :47] if odd else source.frames
    save_video(tmp_path / "out.mp4", frames, source.fps, audio_from=source.audio_path)
    info = probe_video(tmp_path / "out.mp4")
    assert (info.num_frames, info.fps, info.has_audio) == (9, 24.0, True)
    assert (info.height, info.width) == (32, 48)  # odd sides padded by one pixel
    assert audio_seconds(tmp_path / "out.mp4") == pytest.approx(9 / 24, abs=0.03)
    back = load_media(tmp_path / "out.mp4").frames[:, : frames.shape[1], : frames.shape[2]]
    assert np.abs(back - frames).mean() < 0.02


def test_save_video_audio_trimmed_and_absent(tmp_path):
    write_mp4(tmp_path / "long.mp4", num_frames=48, fps=Fraction(24), audio=True)  # 2 s of sound
    frames = np.zeros((6, 16, 16, 3), np.float32)
    save_video(tmp_path / "short.mp4", frames, 24.0, audio_from=tmp_path / "long.mp4", audio_start=1.0)
    assert audio_seconds(tmp_path / "short.mp4") == pytest.approx(0.25, abs=0.03)
    write_mp4(tmp_path / "mute.mp4")
    save_video(tmp_path / "silent.mp4", frames, 24.0, audio_from=tmp_path / "mute.mp4")
    assert not probe_video(tmp_path / "silent.mp4").has_audio
    save_video(tmp_path / "plain.mp4", frames, 12.5)
    assert probe_video(tmp_path / "plain.mp4").fps == 12.5


def test_failed_save_leaves_nothing(tmp_path):
    (tmp_path / "notes.txt").write_text("not audio")
    frames = np.zeros((3, 16, 16, 3), np.float32)
    with pytest.raises(InputError):
        save_video(tmp_path / "out.mp4", frames, 24.0, audio_from=tmp_path / "notes.txt")
    with pytest.raises(InputError):
        save_video(tmp_path / "out.mp4", frames[:0], 24.0)
    assert sorted(os.listdir(tmp_path)) == ["notes.txt"]


# ---------------------------------------------------------------------------------------------
# Resizing
# ---------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    "shape, size, expected",
    [((1080, 1920), 512, (288, 512)), ((1920, 1080), 848, (848, 480)), ((100, 30), 64, (64, 16)), ((10, 10), 8, (16, 16)), ((480, 848), 848, (480, 848))],
)
def test_resize_rounding(shape, size, expected):
    frames = np.random.default_rng(0).random((2, *shape, 3), dtype=np.float32)
    assert resize_frames(frames, size).shape == (2, *expected, 3)


def test_resize_other_multiple():
    frames = np.zeros((1, 100, 300, 3), np.float32)
    assert resize_frames(frames, 256, multiple=32).shape == (1, 96, 256, 3)  # 85.3 → 96


def test_srgb_curves():
    x = np.array([0.0, 0.002, 0.5, 1.0], np.float32)
    encoded = linear_to_srgb(x)
    assert encoded[1] == pytest.approx(12.92 * 0.002) and encoded[2] == pytest.approx(1.055 * 0.5 ** (1 / 2.4) - 0.055)
    assert np.allclose(srgb_to_linear(encoded), x, atol=1e-6)


def test_resize_is_antialiased():
    checker = (np.indices((64, 64)).sum(0) % 2).astype(np.float32)  # 1-pixel checkerboard
    small = resize_frames(np.repeat(checker[None, ..., None], 3, -1), 16)
    assert small.shape == (1, 16, 16, 3) and np.allclose(small, 0.5, atol=0.05)


# ---------------------------------------------------------------------------------------------
# Bad input
# ---------------------------------------------------------------------------------------------


def bad_files(tmp_path) -> dict[str, str]:
    buffer = io.BytesIO()
    Image.fromarray(gradient(64, 64)).save(buffer, format="PNG")
    (tmp_path / "trunc.png").write_bytes(buffer.getvalue()[: len(buffer.getvalue()) // 2])
    (tmp_path / "text.mp4").write_text("this is not a video")
    (tmp_path / "text.png").write_text("this is not an image")
    (tmp_path / "empty.mp4").write_bytes(b"")
    Image.new("L", (9000, 2)).save(tmp_path / "wide.png")  # tiny file, absurd side
    # A PNG header announcing 20000×20000 pixels: Pillow's bomb guard trips before any decoding.
    def chunk(kind: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + kind + data + struct.pack(">I", zlib.crc32(kind + data))

    ihdr = struct.pack(">IIBBBBB", 20000, 20000, 8, 0, 0, 0, 0)
    bomb = b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(b"\0" * 64)) + chunk(b"IEND", b"")
    (tmp_path / "bomb.png").write_bytes(bomb)
    make_frameless_mp4(tmp_path / "zero.mp4")  # an mp4 container with no frames at all
    make_audio_only_mp4(tmp_path / "audio_only.mp4")
    return {
        "trunc.png": "truncated",
        "text.mp4": "not a supported",
        "text.png": "not a supported",
        "empty.mp4": "empty",
        "wide.png": "9000×2",
        "bomb.png": "too large",
        "zero.mp4": "no video stream",
        "audio_only.mp4": "no video stream",
        "missing.mp4": "does not exist",
    }


def test_bad_input_raises_one_sentence(tmp_path):
    for name, fragment in bad_files(tmp_path).items():
        with pytest.raises(InputError) as info:
            load_media(tmp_path / name)
        message = str(info.value)
        assert fragment in message, (name, message)
        assert message.endswith(".") and ". " not in message.replace("e.g. ", ""), message


def test_bad_ranges_and_budget(tmp_path, monkeypatch):
    write_mp4(tmp_path / "v.mp4", num_frames=5)
    for kwargs in [dict(start=5), dict(start=3, end=2), dict(max_frames=0), dict(start=-1)]:
        with pytest.raises(InputError):
            load_video(tmp_path / "v.mp4", **kwargs)
    from relight_core.media import video

    monkeypatch.setattr(video, "MAX_DECODED_PIXELS", 4 * 32 * 48)  # room for 4 frames only
    with pytest.raises(InputError, match="max_frames"):
        load_video(tmp_path / "v.mp4")
    assert load_video(tmp_path / "v.mp4", max_frames=4).frames.shape[0] == 4
