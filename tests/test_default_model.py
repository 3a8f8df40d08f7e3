"""The shipped default model: it is in the repository, trained, and runs on a CPU."""

import numpy as np
import pytest

from relight_core import media
from relight_core.checkpoint import DEFAULT_MODEL_DIR, resolve_model
from relight_core.lighting import load_probe
from relight_core.pipeline import Relighter, RelightRequest


def test_default_resolves_to_the_shipped_trained_model():
    spec, directory = resolve_model("default")
    assert directory == DEFAULT_MODEL_DIR and spec.trained


def _log_edges(frames: np.ndarray) -> np.ndarray:
    """Horizontal and vertical differences of the log grey image, flattened: the reflectance edges,
    which a change of light leaves in place (it multiplies the image; the log adds a smooth field)."""
    grey = np.log(frames.clip(0, 1).mean(-1) + 0.02)
    return np.concatenate([np.diff(grey, axis=-1).ravel(), np.diff(grey, axis=-2).ravel()])


def test_default_model_relights_an_image():
    root = DEFAULT_MODEL_DIR.parent.parent
    relighter = Relighter.load("default", device="cpu")
    frames = media.resize_frames(media.load_media(root / "examples" / "inputs" / "objects.png").frames,
                                 relighter.spec.size)
    results = {name: relighter.relight(RelightRequest(frames, probe=load_probe(root / "envmaps" / f"{name}.exr")))
               for name in ("sunset", "studio")}
    for name, result in results.items():
        assert result.relit.shape == frames.shape and np.isfinite(result.relit).all()
        # A trained model keeps the scene: the log-image edges of its result follow the input's,
        # where an untrained one gives noise (correlation +0.01). Log edges, not pixel values or plain
        # edges: under the studio probe the bright backdrop rightly goes dark, which takes the
        # backdrop's edges with it (plain edges: +0.09 with the shipped model). Measured with the
        # shipped model at its default steps: +0.94 (sunset), +0.32 (studio; +0.30 with its relit refiner at
        # full strength, +0.30 and +0.34 with the relit refiners before, +0.35 without one; a relit refiner that added its correction instead of a
        # smooth gain: +0.08, a haze that washed the dark result out); the DiT before it +0.95, +0.68
        # (it left the studio's backdrop lighter).
        correlation = np.corrcoef(_log_edges(result.relit), _log_edges(frames))[0, 1]
        assert correlation > (0.8 if name == "sunset" else 0.25), (name, correlation)
    # The probe changes the light: the studio probe leaves this scene darker than the sunset
    # (measured mean 0.12 vs 0.32), while the albedo, a property of the scene, barely changes.
    sunset, studio = results["sunset"], results["studio"]
    assert sunset.relit.mean() - studio.relit.mean() > 0.1
    assert np.abs(sunset.albedo - studio.albedo).mean() < np.abs(sunset.relit - studio.relit).mean() / 2


def test_default_model_skips_the_clean_up_call_and_gives_what_it_would_give_with_it():
    """The shipped model's one step lands on x0 at σ 80 (`final_denoise` false): half the DiT's calls. The
    clean-up call at σ_min of the released schedule would apply its residual gains a second time and move the
    result by c_out(σ_min) ≈ 0.002 of the network's output, so the shipped gains are the squares of the ones
    fitted with that call (albedo 0.95² = 0.9025), and the two runs agree to well under a grey level."""
    from dataclasses import replace

    root = DEFAULT_MODEL_DIR.parent.parent
    relighter = Relighter.load("default", device="cpu")
    spec = relighter.spec
    assert not spec.final_denoise and spec.steps == 1
    frames = media.resize_frames(media.load_media(root / "examples" / "inputs" / "objects.png").frames, spec.size)
    request = RelightRequest(frames, probe=load_probe(root / "envmaps" / "sunset.exr"))
    shipped = relighter.relight(request)
    assert shipped.info["evaluations"] == 1
    relighter.spec = replace(spec, final_denoise=True, residual_gain=tuple(g ** 0.5 for g in spec.residual_gain))
    with_call = relighter.relight(request)
    assert with_call.info["evaluations"] == 2
    for clip in ("relit", "albedo"):
        difference = np.abs(getattr(shipped, clip) - getattr(with_call, clip))
        assert difference.max() < 2 / 255 and difference.mean() < 0.1 / 255, clip
    relighter.spec = replace(spec, final_denoise=True)    # the gains applied twice: a visibly different albedo
    assert np.abs(relighter.relight(request).albedo - shipped.albedo).mean() > 1 / 255


@pytest.mark.parametrize("width, height", [(320, 180), (300, 200)])
def test_default_model_relights_wide_photos_at_their_own_resolution(tmp_path, width, height):
    # 16:9 and 3:2, the shapes of most videos and photos: at the model's 128 px they are 128×72 and 128×88 (not
    # multiples of 16, which the pixel tokenizer once demanded), and come back at the input's size.
    from relight_core.jobs import MediaJob, load_inputs, plan_job, write_job
    from relight_core.media.image import resize

    root = DEFAULT_MODEL_DIR.parent.parent
    source = media.load_media(root / "examples" / "inputs" / "objects.png").frames
    path = tmp_path / "wide.png"
    media.save_image(path, resize(source, height, width)[0])
    relighter = Relighter.load("default", device="cpu")
    job = MediaJob(mode="relight", input=path, probe=root / "envmaps" / "sunset.exr")
    inputs = load_inputs(job)
    plan = plan_job(job, relighter, inputs)
    assert plan.frames.shape[1:3] == media.target_size(height, width, 128, 8) == (round(128 * height / width / 8) * 8, 128)
    written = write_job(job, relighter, inputs, plan, tmp_path / "out")
    assert sorted(p.name for p in written) == ["albedo.png", "relit.png"]
    for p in written:
        frames = media.load_media(p).frames
        assert frames.shape == (1, height, width, 3)
        # the scene is kept: log edges follow the input's as in the square test above (measured: relit 0.97 / 0.98,
        # albedo 0.84 / 0.82 for 16:9 / 3:2; an untrained model ~0.01)
        assert np.corrcoef(_log_edges(frames), _log_edges(inputs.source.frames))[0, 1] > 0.7, p.name


def test_default_model_beats_the_input_copy_floor_on_held_out_scenes_it_renders(tmp_path):
    """The first two scenes of the held-out test split (probes, meshes and textures training never
    uses), rendered here with Mitsuba at the test data's size (128 px, or the model's if larger) and
    scored with `evaluate`'s protocol through the whole pipeline (a model trained smaller runs at its
    size and its results come back by guided ratio upsampling, as users get them): the shipped
    model's relit and albedo must beat the input returned unchanged (the floor), on average over
    both directions of both scenes. Measured with the shipped model (128 px) at 16 spp, 128 px: relit
    23.32 dB against a floor of 21.97 (23.24 with its relit refiner at full strength, 23.21 and 23.37 with the
    relit refiners before, 22.96 without one), albedo
    23.34 against 17.37 (23.37, 23.30, 23.22, 23.04 and 22.88 with the albedo refiners shipped before, 22.18
    without a refiner)."""
    pytest.importorskip("mitsuba")
    from relight_core.data.generate import RenderConfig, render_dataset
    from relight_core.evaluation.harness import RunOptions, load_items, mean_metrics, measure_item

    relighter = Relighter.load("default", device="cpu")
    render_dataset(RenderConfig(out=tmp_path, scenes=2, frames=1, size=max(relighter.spec.size, 128), spp=16, workers=1,
                                split="test"), progress=False)
    items = load_items(tmp_path, "test")
    assert len(items) == 4  # two scenes, both directions
    records = [measure_item(relighter, item, RunOptions(), margin=False)[0] for item in items]
    for clip in ("relit", "albedo"):
        model, floor = (mean_metrics(records, kind, clip, "psnr") for kind in ("model", "floor"))
        assert model > floor, f"{clip}: model {model:.2f} dB is not above the input-copy floor {floor:.2f} dB"


def test_default_model_keeps_the_still_parts_of_a_video_steady():
    """The example orbit video (a real MP4): the shipped model relights frame by frame, and its temporal filter
    (`temporal_filter`, relight_core/temporal.py) averages each frame's own mistakes with its neighbours' where the
    input holds still. Measured on its first 9 frames under the sunset probe, on the 78 % of pixels whose input
    changes by < 0.02 from one frame to the next: the relit result changed by RMS 0.0113 a frame without the
    filter (twice the input's own 0.0059), 0.0031 with it; the albedo 0.0152 → 0.0039; the results moved by 0.007
    on average."""
    from dataclasses import replace

    root = DEFAULT_MODEL_DIR.parent.parent
    relighter = Relighter.load("default", device="cpu")
    assert relighter.spec.temporal_filter[0] > 0
    frames = media.resize_frames(media.load_media(root / "examples" / "inputs" / "orbit.mp4").frames[:6],
                                 relighter.spec.size)
    request = RelightRequest(frames, probe=load_probe(root / "envmaps" / "sunset.exr"))
    steady = relighter.relight(request)
    relighter.spec = replace(relighter.spec, temporal_filter=(0,) + relighter.spec.temporal_filter[1:])
    raw = relighter.relight(request)
    still = np.abs(np.diff(frames, axis=0)).max(-1) < 0.02

    def change(x):  # RMS frame-to-frame change where the input holds still
        return float(np.sqrt((np.diff(x, axis=0) ** 2).mean(-1)[still].mean()))

    assert still.mean() > 0.5
    for clip in ("relit", "albedo"):
        a, b = getattr(steady, clip), getattr(raw, clip)
        assert change(a) < 0.5 * change(b) and change(a) < change(frames), (clip, change(a), change(b))
        assert np.abs(a - b).mean() < 0.02


def test_default_model_moves_shadows_with_the_light_and_takes_them_out_of_the_albedo():
    """Issue 7's visible criteria on a held-out scene rendered here (test scene 0, its input under its own probe)
    relit under the held-out sunset probe (a low sun) turned half a turn (relight_core/evaluation/light_follow.py;
    runs/shadow-follow/ scores 24 scenes at four yaws). Measured at 16 spp (bf16 by auto, AVX512-BF16): the
    results change where the renders do (follow 0.57; a model that ignores the light 0), 0.88 of the pixels whose
    light changes by more than 1.5× change the same way (0.5 by chance), and the albedo keeps 0.19 and 0.13 of the
    input's shading (the input copied: 1)."""
    pytest.importorskip("mitsuba")
    from relight_core.data.scenes import sample_scene
    from relight_core.evaluation import light_follow as lf
    from relight_core.evaluation.harness import RunOptions, relight

    relighter = Relighter.load("default", device="cpu")
    scene = lf.render_turned(sample_scene(0, "test", 0, 1), "file:sunset", (0.0, 180.0), size=128, spp=16)
    (relit_a, albedo_a, _), (relit_b, albedo_b, _) = (relight(relighter, scene.source[None], probe[None], RunOptions())
                                                      for probe in scene.probes)
    (target_a, target_b), mask = scene.targets, scene.mask
    assert lf.change_follow(target_a, target_b, relit_a[0], relit_b[0], mask) > 0.4
    assert lf.shadow_agreement(target_a, target_b, relit_a[0], relit_b[0], mask) > 0.75
    for albedo in (albedo_a, albedo_b):
        assert lf.albedo_shading(albedo[0], scene.albedo, scene.source, mask) < 0.4
