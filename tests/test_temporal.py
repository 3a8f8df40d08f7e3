"""The input-guided filter along time that steadies an image model's video results (relight_core/temporal.py)."""
import numpy as np
import pytest
import torch

from relight_core import lighting
from relight_core.checkpoint import ModelSpec
from relight_core.dit import DiTConfig, JointDiT
from relight_core.errors import InputError
from relight_core.pipeline import ChunkDone, Finished, Relighter, RelightRequest
from relight_core.temporal import light_descriptor, light_distances, temporal_filter
from relight_core.tokenizer import build_tokenizer


def test_two_frames_mix_by_the_weight_computed_by_hand():
    rng = np.random.default_rng(0)
    guide = rng.random((2, 4, 5, 3)).astype(np.float32)
    out = rng.random((2, 4, 5, 3)).astype(np.float32)
    distances = np.array([[0.2, 0.0]])                  # frame 0 to frame 1: 0.2
    (got,) = temporal_filter(guide, [out], radius=1, sigma=0.3, light=0.5, distances=distances)
    w = np.exp(-((guide[0] - guide[1]) ** 2).sum(-1, keepdims=True) / (2 * 0.3 ** 2)) * np.exp(-(0.2 / 0.5) ** 2)
    np.testing.assert_allclose(got[0], (out[0] + w * out[1]) / (1 + w), rtol=1e-5)
    np.testing.assert_allclose(got[1], (out[1] + w * out[0]) / (1 + w), rtol=1e-5)


def test_a_long_video_filtered_in_blocks_is_the_same_as_in_one_go():
    rng = np.random.default_rng(4)
    guide = rng.random((23, 6, 5, 3)).astype(np.float32) * 0.1
    out = rng.random((23, 6, 5, 3)).astype(np.float32)
    turned = np.tile(np.array([[0.1], [0.2], [0.3]]), (1, 23)) * rng.random(23)
    whole = temporal_filter(guide, [out, out[..., :1]], 3, 0.08, 0.3, distances=turned, block=1000)
    for block in (1, 4, 7):
        blocks = temporal_filter(guide, [out, out[..., :1]], 3, 0.08, 0.3, distances=turned, block=block)
        for a, b in zip(whole, blocks):
            np.testing.assert_allclose(a, b, rtol=1e-6)
    assert not np.allclose(whole[0], out, atol=1e-2)


def test_a_still_input_averages_away_each_frames_own_mistakes_and_keeps_what_moves():
    rng = np.random.default_rng(1)
    frames, size = 9, 16
    guide = np.full((frames, size, size, 3), 0.5, np.float32)
    truth = np.tile(rng.random((1, size, size, 3)).astype(np.float32), (frames, 1, 1, 1))
    guide[4, :4, :4] = 0.0                       # something passes through one corner in frame 4 …
    truth[4, :4, :4] = 1.0                       # … and the result there must change with it
    noisy = truth + rng.normal(0, 0.05, truth.shape).astype(np.float32)
    (steady,) = temporal_filter(guide, [noisy], radius=3, sigma=0.05, light=0.3)
    still = np.ones(truth.shape[:3], bool)
    still[:, :4, :4] = False
    assert np.sqrt(((steady - truth) ** 2)[still].mean()) < 0.5 * np.sqrt(((noisy - truth) ** 2)[still].mean())
    np.testing.assert_allclose(steady[4, :4, :4], noisy[4, :4, :4], atol=1e-6)   # weights ~e^-37: its own
    (same,) = temporal_filter(guide, [truth], radius=3, sigma=0.05, light=0.3)
    np.testing.assert_allclose(same, truth, atol=1e-6)                           # a steady result stays


def test_frames_under_another_light_keep_their_own_results():
    guide = np.zeros((3, 4, 4, 3), np.float32)
    out = np.stack([np.full((4, 4, 3), v, np.float32) for v in (0.1, 0.5, 0.9)])
    turned = np.array([[5.0, 5.0, 0], [5.0, 0, 0]])      # one frame apart; two apart
    (kept,) = temporal_filter(guide, [out], radius=2, sigma=0.05, light=0.3, distances=turned)
    np.testing.assert_allclose(kept, out, atol=1e-6)
    (mixed,) = temporal_filter(guide, [out], radius=2, sigma=0.05, light=0.3, distances=np.zeros((2, 3)))
    np.testing.assert_allclose(mixed, np.full_like(out, 0.5), atol=1e-6)
    for radius, clip in ((0, out), (2, out[:1])):                                # off, or a single image
        np.testing.assert_array_equal(temporal_filter(guide[:len(clip)], [clip], radius, 0.05, 0.3)[0], clip)


def test_light_distances_are_zero_for_the_same_light_and_grow_as_it_turns():
    probe = torch.full((32, 64, 3), 0.2)
    probe[8:10, 10:12] = 200.0                                                   # a small sun
    panoramas = torch.stack([lighting.probe_in_camera(probe, 32, 64, rotation=r) for r in (0, 0, 10, 90)])
    d = light_distances(light_descriptor(panoramas), 3)           # row k − 1: frame t to frame t + k
    assert d.shape == (3, 4) and np.all(d[0, 3:] == 0) and np.all(d[2, 1:] == 0)
    assert d[0, 0] < 1e-9 and 0 < d[1, 0] < d[2, 0] and d[1, 0] == pytest.approx(d[0, 1])


def _relighter(settings):
    torch.manual_seed(0)
    config = DiTConfig(width=32, depth=1, num_heads=2, patch_spatial=1, patch_temporal=1, out_channels=192,
                       cross_attention=False, adaln_lora_dim=8)
    dit = JointDiT(config)
    torch.nn.init.normal_(dit.final_layer.linear.weight, std=0.05)              # results that differ per frame
    spec = ModelSpec(name="t", dit=config, tokenizer={"type": "pixel", "patch": 8}, chunk_frames=1,
                     overlap_frames=0, size=32, steps=1, lighting_size=8, residual=True, temporal_filter=settings)
    return Relighter(spec, dit, build_tokenizer({"type": "pixel", "patch": 8}))


@pytest.mark.parametrize("turning", [False, True])
def test_the_pipeline_filters_a_videos_results_with_its_lights_distances(turning):
    rng = np.random.default_rng(2)
    base = rng.random((1, 32, 32, 3)).astype(np.float32)
    frames = np.clip(base + rng.normal(0, 0.01, (5, 32, 32, 3)), 0, 1).astype(np.float32)
    probe = np.ones((16, 32, 3), np.float32)
    probe[4:6, 8:10] = 50.0
    request = RelightRequest(frames=frames, probe=probe, rotate_light=turning, sweep=(0.0, 180.0))
    relighter = _relighter((2, 0.05, 0.3))
    chunks, result = [], None
    for event in relighter.run(request):
        if isinstance(event, ChunkDone):
            chunks.append(event.relit)
        elif isinstance(event, Finished):
            result = event.result
    raw = np.concatenate(chunks)
    rotations = lighting.frame_rotations(5, request.rotation, request.rotate_light, request.sweep)
    descriptors = relighter._light_descriptors(request, relighter._prepared_probe(request), rotations)
    distances = light_distances(descriptors, 2)
    assert (distances[0, 0] > 0.05) == turning                                   # a sweep turns the light
    expected = temporal_filter(frames, [raw], 2, 0.05, 0.3, distances=distances)[0]
    np.testing.assert_allclose(result.relit, expected, atol=1e-5)
    assert not np.allclose(result.relit, raw, atol=1e-3)                         # it did filter
    plain = _relighter((0, 0.05, 0.3)).relight(request)                         # off: the frames as they came
    np.testing.assert_allclose(plain.relit, raw, atol=1e-5)


def test_the_setting_round_trips_through_config_json_and_bad_values_are_refused_in_one_sentence():
    spec = _relighter((3, 0.08, 0.3)).spec
    assert ModelSpec.from_json(spec.to_json()).temporal_filter == (3, 0.08, 0.3)
    data = spec.to_json()
    del data["temporal_filter"]
    assert ModelSpec.from_json(data).temporal_filter[0] == 0                     # older folders: off
    for bad in ([3, 0.08], [-1, 0.1, 0.3], [3, 0, 0.3], [3, float("nan"), 0.3], [True, 0.1, 0.3], "3", [17, 0.1, 1]):
        with pytest.raises(InputError, match="temporal_filter"):
            ModelSpec.from_json({**spec.to_json(), "temporal_filter": bad})


def test_per_frame_skips_the_filter_from_the_cli_down_to_the_pipeline(tmp_path):
    from relight_core import media
    from relight_core.cli import _media_job, build_parser
    from relight_core.jobs import load_inputs, plan_job
    from tests.factory import write_exr

    relighter = _relighter((2, 0.05, 0.3))
    rng = np.random.default_rng(3)
    frames = np.clip(rng.random((1, 32, 32, 3)) + rng.normal(0, 0.01, (4, 32, 32, 3)), 0, 1).astype(np.float32)
    request = RelightRequest(frames=frames, probe=np.ones((16, 32, 3), np.float32))
    steady, raw = relighter.relight(request), relighter.relight(RelightRequest(**{**vars(request), "per_frame": True}))
    np.testing.assert_allclose(raw.relit, _relighter((0, 0.05, 0.3)).relight(request).relit, atol=1e-6)
    assert not np.allclose(steady.relit, raw.relit, atol=1e-3)
    video = tmp_path / "clip.mp4"
    media.save_video(video, frames, 12.0)
    write_exr(tmp_path / "probe.exr", np.ones((16, 32, 3), np.float32))
    for flags, expected in (([], False), (["--per-frame"], True)):
        args = build_parser().parse_args(["relight", str(video), "--probe", str(tmp_path / "probe.exr"),
                                          "--out", str(tmp_path / "out"), *flags])
        job = _media_job(args)
        plan = plan_job(job, relighter, load_inputs(job))
        assert job.per_frame is expected and all(r.per_frame is expected for _, r in plan.requests)
