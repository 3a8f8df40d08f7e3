"""The Relighter pipeline on the tiny preset: modes, streaming, chunking, caching, determinism."""

import threading

import numpy as np
import pytest

from relight_core.errors import InputError
from relight_core.chunking import crossfade_weights, pad_to_valid, plan_chunks, stitch
from relight_core.pipeline import ChunkDone, Finished, Progress, Relighter, RelightRequest
from tests.factory import awake


@pytest.fixture(scope="module")
def relighter():
    return awake(Relighter.load("tiny", device="cpu"))


@pytest.fixture(scope="module")
def probe():
    """A dim sky with one bright sun."""
    env = np.full((16, 32, 3), 0.2, np.float32)
    env[4, 8] = 500.0
    return env


def _frames(t=1, h=32, w=48, seed=0):
    return np.random.default_rng(seed).random((t, h, w, 3), dtype=np.float32)


def _events(relighter, request):
    return list(relighter.run(request))


# ---- chunk planning -------------------------------------------------------------------------

@pytest.mark.parametrize("num_frames", [1, 9, 17, 18, 40, 100])
def test_chunks_cover_every_frame_with_the_overlap(num_frames):
    chunks = plan_chunks(num_frames, chunk=17, overlap=9)
    covered = np.zeros(num_frames, bool)
    for start, length in chunks:
        covered[start:start + length] = True
        assert length <= 17 and start + length <= num_frames
    assert covered.all()
    for (s0, l0), (s1, _) in zip(chunks, chunks[1:]):
        assert s0 + l0 - s1 >= 9, "consecutive chunks must share at least the overlap"
    if num_frames >= 17:
        assert all(length == 17 for _, length in chunks)


def test_pad_to_valid_repeats_the_last_frame():
    frames = np.arange(5, dtype=np.float32)[:, None, None, None] * np.ones((5, 2, 2, 3), np.float32)
    padded = pad_to_valid(frames, 8)
    assert padded.shape[0] == 9
    assert np.all(padded[5:] == frames[-1])
    assert pad_to_valid(frames[:1], 8).shape[0] == 1


def test_crossfade_weights_rise_inside_the_unit_interval():
    w = crossfade_weights(9)
    assert w.shape == (9,) and np.all(np.diff(w) > 0) and w[0] > 0 and w[-1] < 1


def test_stitch_blends_the_shared_frames():
    out = np.zeros((10, 1, 1, 3), np.float32)
    stitch(out, np.zeros((6, 1, 1, 3), np.float32), 0, None)
    stitch(out, np.ones((6, 1, 1, 3), np.float32), 4, crossfade_weights(2))
    np.testing.assert_allclose(out[:, 0, 0, 0], [0, 0, 0, 0, 1 / 3, 2 / 3, 1, 1, 1, 1], atol=1e-6)


# ---- one image ------------------------------------------------------------------------------

def test_relight_image_streams_previews_then_the_result(relighter, probe):
    events = _events(relighter, RelightRequest(_frames(), probe=probe, steps=3, seed=1))
    progress = [e for e in events if isinstance(e, Progress)]
    assert len(progress) == 4, "res2ab at guidance 0: steps + 1 denoiser evaluations"
    assert [p.evaluation for p in progress] == [1, 2, 3, 4] and {p.evaluations for p in progress} == {4}
    assert [p.step for p in progress] == [1, 2, 3, 3]  # as chosen: the clean-x0 call ends step 3
    assert all(p.relit_preview.shape == (32, 48, 3) and p.albedo_preview.shape == (32, 48, 3) for p in progress)
    assert progress[-1].eta_s == pytest.approx(0.0, abs=1e-6)
    assert isinstance(events[-1], Finished) and sum(isinstance(e, Finished) for e in events) == 1
    result = events[-1].result
    assert result.relit.shape == (1, 32, 48, 3) and result.albedo.shape == (1, 32, 48, 3)
    assert result.relit.min() >= 0 and result.relit.max() <= 1
    assert result.info["evaluations"] == 4


def test_same_seed_same_output_other_seed_other_output(relighter, probe):
    a = relighter.relight(RelightRequest(_frames(), probe=probe, steps=2, seed=7))
    b = relighter.relight(RelightRequest(_frames(), probe=probe, steps=2, seed=7))
    c = relighter.relight(RelightRequest(_frames(), probe=probe, steps=2, seed=8))
    np.testing.assert_array_equal(a.relit, b.relit)
    np.testing.assert_array_equal(a.albedo, b.albedo)
    assert not np.array_equal(a.relit, c.relit)


def test_guidance_doubles_the_evaluations(relighter, probe):
    result = relighter.relight(RelightRequest(_frames(), probe=probe, steps=2, guidance=1.5))
    assert result.info["evaluations"] == 2 * 3
    progress = [e for e in _events(relighter, RelightRequest(_frames(), probe=probe, steps=2, guidance=1.5))
                if isinstance(e, Progress)]
    assert [(p.evaluation, p.evaluations, p.step) for p in progress] == [(2, 6, 1), (4, 6, 2), (6, 6, 2)]


def test_a_model_without_the_clean_up_call_makes_one_call_a_step_and_counts_its_steps(probe):
    from dataclasses import replace

    relighter = awake(Relighter.load("tiny", device="cpu"))
    with_call = relighter.estimate_seconds(1, 32, 48, steps=3)
    relighter.spec = replace(relighter.spec, final_denoise=False)
    relighter._overhead_per_pixel = 0.0
    without_overhead = relighter.estimate_seconds(1, 32, 48, steps=3)
    relighter.spec = replace(relighter.spec, final_denoise=True)
    assert relighter.estimate_seconds(1, 32, 48, steps=3) == pytest.approx(4 / 3 * without_overhead)
    assert with_call > without_overhead
    relighter.spec = replace(relighter.spec, final_denoise=False)
    events = _events(relighter, RelightRequest(_frames(), probe=probe, steps=3, seed=1))
    progress = [e for e in events if isinstance(e, Progress)]
    assert [(p.evaluation, p.evaluations, p.step) for p in progress] == [(1, 3, 1), (2, 3, 2), (3, 3, 3)]
    assert events[-1].result.info["evaluations"] == 3 and progress[-1].eta_s == pytest.approx(0.0, abs=1e-6)
    guided = [e for e in _events(relighter, RelightRequest(_frames(), probe=probe, steps=2, guidance=1.5))
              if isinstance(e, Progress)]
    assert [(p.evaluation, p.evaluations, p.step) for p in guided] == [(2, 4, 1), (4, 4, 2)]
    heun = [e for e in _events(relighter, RelightRequest(_frames(), probe=probe, steps=3, sampler="heun"))
            if isinstance(e, Progress)]                 # two calls a step, one for the last step to 0
    assert [(p.evaluation, p.evaluations, p.step) for p in heun] == [(1, 5, 1), (2, 5, 1), (3, 5, 2), (4, 5, 2),
                                                                     (5, 5, 3)]


def test_probe_rotation_changes_the_result(relighter, probe):
    a = relighter.relight(RelightRequest(_frames(), probe=probe, steps=2, rotation=0.0))
    b = relighter.relight(RelightRequest(_frames(), probe=probe, steps=2, rotation=90.0))
    assert not np.array_equal(a.relit, b.relit)


def test_changing_only_the_probe_does_not_re_encode_the_input(probe):
    relighter = awake(Relighter.load("tiny", device="cpu"))
    encoded = []
    original = relighter.tokenizer.encode
    relighter.tokenizer.encode = lambda video: (encoded.append(video.shape), original(video))[1]
    frames = _frames(seed=3)
    relighter.relight(RelightRequest(frames, probe=probe, steps=1, rotation=10.0))
    first = len(encoded)
    relighter.relight(RelightRequest(frames, probe=probe, steps=1, rotation=20.0))
    # Only the three lighting encodings (ldr, log, dir) are new; the input latent is cached.
    assert len(encoded) - first == 3
    relighter.relight(RelightRequest(frames, probe=probe, steps=1, rotation=20.0))
    assert len(encoded) - first == 3, "the same probe and rotation hit the cache too"


# ---- modes ----------------------------------------------------------------------------------

def test_albedo_mode_needs_no_probe(relighter):
    result = relighter.relight(RelightRequest(_frames(), mode="albedo", steps=1))
    assert result.albedo.shape == (1, 32, 48, 3)


def test_random_mode_gives_a_different_illumination_per_seed(relighter, probe):
    """The illumination comes from the seed alone: each seed reproduces its own result, seeds differ,
    and a probe in the request plays no part (random mode gives the network no lighting)."""
    def run(seed, **light):
        return relighter.relight(RelightRequest(_frames(), mode="random", steps=2, seed=seed, **light)).relit

    a, b = run(0), run(1)
    assert not np.array_equal(a, b)
    np.testing.assert_array_equal(run(0), a)
    np.testing.assert_array_equal(run(0, probe=probe, rotation=90.0), a)
    lit = relighter.relight(RelightRequest(_frames(), mode="relight", probe=probe, steps=2, seed=0)).relit
    assert not np.allclose(lit, a, atol=1e-3), "lighting changes this network's output: the check above means something"


def test_render_mode_uses_the_albedo_not_the_input(relighter, probe):
    def render(input_seed, albedo_seed):
        return relighter.relight(RelightRequest(_frames(seed=input_seed), mode="render", probe=probe,
                                                albedo=_frames(seed=albedo_seed), steps=2)).relit

    a = render(1, 5)
    np.testing.assert_array_equal(render(2, 5), a)                       # another input: the same render
    assert np.abs(render(1, 6) - a).mean() > 1e-3                        # another albedo: another render


@pytest.mark.parametrize("kwargs, words", [
    (dict(mode="relight"), "needs an HDR probe"),
    (dict(mode="render", probe=np.ones((8, 16, 3), np.float32)), "albedo"),
    (dict(mode="dream"), "Unknown mode"),
    (dict(mode="albedo", sampler="ddim"), "Unknown sampler"),
    (dict(mode="albedo", steps=0), "Steps"),
    (dict(mode="albedo", guidance=float("nan")), "Guidance"),
])
def test_bad_requests_raise_one_sentence(relighter, kwargs, words):
    with pytest.raises(InputError, match=words):
        relighter.relight(RelightRequest(_frames(), **kwargs))


def test_frame_size_must_fit_the_tokenizer(relighter):
    with pytest.raises(InputError, match="multiples of 16"):
        relighter.relight(RelightRequest(_frames(h=30), mode="albedo", steps=1))


# ---- videos ---------------------------------------------------------------------------------

def test_long_video_runs_in_chunks_and_keeps_its_length(relighter, probe):
    frames = _frames(t=25, h=16, w=32)
    events = _events(relighter, RelightRequest(frames, probe=probe, steps=1, rotate_light=True))
    chunks = [e for e in events if isinstance(e, ChunkDone)]
    assert [c.chunk for c in chunks] == [0, 1] and chunks[1].start == 8
    assert all(c.relit.shape == (17, 16, 32, 3) for c in chunks)
    result = events[-1].result
    assert result.relit.shape == frames.shape and result.info["chunks"] == 2
    # Frames before the overlap come from chunk 0 alone, frames after it from chunk 1 alone.
    np.testing.assert_array_equal(result.relit[:8], chunks[0].relit[:8])
    np.testing.assert_array_equal(result.relit[17:], chunks[1].relit[9:])
    shared = slice(8, 17)
    lo = np.minimum(chunks[0].relit[8:], chunks[1].relit[:9]) - 1e-6
    hi = np.maximum(chunks[0].relit[8:], chunks[1].relit[:9]) + 1e-6
    assert np.all((lo <= result.relit[shared]) & (result.relit[shared] <= hi)), "shared frames are blends"
    # Each ChunkDone carries the video so far exactly as the result stitches it (the studio shows it).
    np.testing.assert_array_equal(chunks[0].stitched_relit, chunks[0].relit)
    np.testing.assert_array_equal(chunks[-1].stitched_relit, result.relit)
    np.testing.assert_array_equal(chunks[-1].stitched_albedo, result.albedo)


def test_a_last_chunk_flush_with_the_end_conditions_on_a_causal_prefix(relighter, probe):
    result = relighter.relight(RelightRequest(_frames(t=26, h=16, w=16), probe=probe, steps=1))
    assert result.relit.shape == (26, 16, 16, 3) and result.info["chunks"] == 3


def test_video_shorter_than_a_valid_length_is_padded_and_trimmed(relighter, probe):
    result = relighter.relight(RelightRequest(_frames(t=5, h=16, w=16), probe=probe, steps=1))
    assert result.relit.shape == (5, 16, 16, 3)


# ---- stopping -------------------------------------------------------------------------------

def test_should_stop_ends_the_run_without_a_result(relighter, probe):
    calls = []
    request = RelightRequest(_frames(), probe=probe, steps=6, should_stop=lambda: len(calls) >= 2)
    events = []
    for event in relighter.run(request):
        events.append(event)
        calls.append(1)
    assert not any(isinstance(e, Finished) for e in events)
    assert len([e for e in events if isinstance(e, Progress)]) < 7


def test_closing_the_stream_stops_the_sampler_thread(relighter, probe):
    gen = relighter.run(RelightRequest(_frames(), probe=probe, steps=8))
    assert isinstance(next(gen), Progress)
    gen.close()
    assert not any(t.name == "relight-sampler" and t.is_alive() for t in threading.enumerate())


def test_estimate_seconds_grows_with_the_work(relighter):
    short = relighter.estimate_seconds(1, 64, 64, steps=10)
    long = relighter.estimate_seconds(60, 64, 64, steps=10)
    assert 0 < short < long


def test_estimate_scales_with_size_after_a_measured_run(probe):
    relighter = Relighter.load("tiny", device="cpu")
    relighter.relight(RelightRequest(_frames(), probe=probe, steps=2))
    small = relighter.estimate_seconds(1, 32, 48, steps=2)
    large = relighter.estimate_seconds(1, 256, 384, steps=2)
    assert relighter._flops_per_second > 0 and large > 10 * small


def test_warm_up_measures_this_machine_and_the_estimate_adds_network_and_per_pixel_costs(probe):
    """The estimate comes from this machine's measured network speed and its measured per-pixel cost
    outside the network (lighting, encode, decode), not from an assumed constant. (How close it comes
    to a real run is a timing, so `bench` reports it; here, the arithmetic.)"""
    relighter = Relighter.load("tiny", device="cpu")
    assert relighter.warm_up() > 0
    assert relighter._flops_per_second > 0 and relighter._overhead_per_pixel > 0
    relighter._flops_per_second, relighter._overhead_per_pixel = 1e9, 1e-6
    tokens = 3 * 1 * (64 // relighter.frame_multiple) ** 2
    network = relighter._flops_per_eval(tokens) / 1e9
    assert relighter.estimate_seconds(1, 64, 64, steps=4) == pytest.approx(5 * network + 64 * 64 * 1e-6)
    relighter._overhead_per_pixel *= 10  # a slower decode shows in the estimate
    assert relighter.estimate_seconds(1, 64, 64, steps=4) == pytest.approx(5 * network + 64 * 64 * 1e-5)
