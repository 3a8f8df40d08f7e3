"""Does a result follow the light where it matters — do shadows move when the probe turns, and does the albedo
lose the input's shadows? Issue 7 asks for both "visibly"; these put a number on them (runs/shadow-follow/).

A scene is rendered under its own probe (the input) and under one probe turned to several world yaws (the
targets); the model relights the input under each. Between two yaws the truth brightens here and darkens there
(a cast shadow leaves, a highlight arrives); the result should change in the same places:

* `change_follow`: the Pearson correlation, over the mask, of the result's log-luminance change
  log(out_a / out_b) with the truth's log(target_a / target_b): 1 when it changes where the truth does, 0 for a
  result that does not change (a model that ignores the light). With `sigma`, both changes less their Gaussian
  blur first: the sharp part of the change (a cast shadow's edge), which no smooth gain can make;
* `change_reach`: the regression slope of the result's change on the truth's (1: the whole change, 0: none);
* `shadow_agreement`: on the pixels whose truth changes by more than a factor 1.5, the fraction whose result
  changes the same way (0.5 by chance);
* `albedo_shading`: the regression slope, over the mask, of log(albedo / true albedo) on the input's shading
  log(input / true albedo) — 1 when the albedo keeps the input's shading and shadows (the input copied), 0 when
  none of it is left. Scale-free, as the protocol's per-channel fit is: a constant factor moves only the mean.

Images are display values in [0, 1] ([H,W,3]); luminance is taken of the linear values.
"""

from __future__ import annotations

import dataclasses
from itertools import combinations
from typing import Callable

import cv2
import numpy as np

from relight_core.colour import linear_to_srgb, luminance, srgb_to_linear
from relight_core.media.image import to_uint8

EPS = 1e-3          # linear luminance added before the log: black pixels stay finite
STRONG = np.log(1.5)  # a change by more than this factor counts for `shadow_agreement`
PROBE = "file:sunset"  # held out from training: a low sun, long hard shadows
YAWS = (0.0, 90.0, 180.0, 270.0)
DETAIL_SIGMA = 3.0
KEYS = ("follow", "follow_ceiling", "follow_detail", "follow_detail_ceiling", "reach", "shadow_agreement",
        "albedo_shading")


def log_luminance(srgb: np.ndarray) -> np.ndarray:
    """log(Y + EPS) of display values [..., 3] (Rec. 709 luminance of the linear values)."""
    return np.log(luminance(srgb_to_linear(np.clip(np.asarray(srgb, np.float64), 0, 1))) + EPS)


def _change(a: np.ndarray, b: np.ndarray, sigma: float | None) -> np.ndarray:
    change = log_luminance(a) - log_luminance(b)
    if sigma:
        change = change - cv2.GaussianBlur(change.astype(np.float32), (0, 0), sigma).astype(np.float64)
    return change


def _correlation(x: np.ndarray, y: np.ndarray) -> float:
    x, y = x - x.mean(), y - y.mean()
    denominator = np.sqrt((x * x).sum() * (y * y).sum())
    return float((x * y).sum() / denominator) if denominator > 1e-12 else 0.0


def _slope(y: np.ndarray, x: np.ndarray) -> float:
    x, y = x - x.mean(), y - y.mean()
    return float((x * y).sum() / max((x * x).sum(), 1e-12))


def change_follow(truth_a, truth_b, out_a, out_b, mask, sigma: float | None = None) -> float:
    """Correlation of the result's change between two lights with the truth's, over the mask (see above)."""
    m = np.asarray(mask) > 0.5
    return _correlation(_change(truth_a, truth_b, sigma)[m], _change(out_a, out_b, sigma)[m])


def change_reach(truth_a, truth_b, out_a, out_b, mask) -> float:
    """How much of the truth's change the result makes: the slope of its change on the truth's."""
    m = np.asarray(mask) > 0.5
    return _slope(_change(out_a, out_b, None)[m], _change(truth_a, truth_b, None)[m])


def shadow_agreement(truth_a, truth_b, out_a, out_b, mask, least: int = 20) -> float | None:
    """Of the mask pixels whose truth changes by more than a factor 1.5, the fraction whose result changes
    the same way; None when fewer than `least` pixels change that much."""
    m = np.asarray(mask) > 0.5
    truth, made = _change(truth_a, truth_b, None)[m], _change(out_a, out_b, None)[m]
    strong = np.abs(truth) > STRONG
    if strong.sum() < least:
        return None
    return float((np.sign(made[strong]) == np.sign(truth[strong])).mean())


def albedo_shading(albedo, true_albedo, source, mask) -> float:
    """How much of the input's shading the albedo keeps: 1 all of it (the input copied), 0 none."""
    m = np.asarray(mask) > 0.5
    shading = (log_luminance(source) - log_luminance(true_albedo))[m]
    return _slope((log_luminance(albedo) - log_luminance(true_albedo))[m], shading)


@dataclasses.dataclass
class TurnedScene:
    """A scene under its own first probe (`source`) and under one probe at several world yaws."""

    source: np.ndarray          # [H,W,3] display values, as the dataset's PNGs hold them
    albedo: np.ndarray          # [H,W,3] display values
    mask: np.ndarray            # [H,W] 1 = geometry
    targets: list[np.ndarray]   # per yaw, [H,W,3] display values
    probes: list[np.ndarray]    # per yaw, the camera-frame panorama the model is given
    again: list[np.ndarray]     # per yaw, the target rendered once more with other noise (`again=True`), or []


def _display(linear: np.ndarray) -> np.ndarray:
    return to_uint8(linear_to_srgb(linear)) / 255.0  # as the dataset's 8-bit PNGs hold it


def render_turned(spec, probe: str, yaws, size: int = 128, spp: int = 32, exposure: float = 0.7,
                  again: bool = False) -> TurnedScene:
    """Render `spec` (a data-engine scene, one frame) under its first probe and under `probe` (a probe source,
    e.g. "file:sunset") at each world yaw in `yaws` (degrees), with Mitsuba; `again` renders each target a
    second time with other noise (the ceilings)."""
    from relight_core.data.generate import frame_seed
    from relight_core.data.probes import ProbeChoice
    from relight_core.data.render import SceneRenderer

    seed = frame_seed(spec, 0)
    with SceneRenderer(spec, size, spp) as renderer:
        source = _display(renderer.render(0, 0, seed))
        albedo, mask = renderer.render_aovs(0, seed)
    targets, probes, repeats = [], [], []
    for yaw in yaws:
        turned = dataclasses.replace(spec, probes=(spec.probes[0], ProbeChoice(probe, 0, float(yaw), exposure)))
        with SceneRenderer(turned, size, spp) as renderer:
            targets.append(_display(renderer.render(0, 1, seed)))
            probes.append(renderer.camera_probe(0, 1))
            if again:
                repeats.append(_display(renderer.render(0, 1, seed + 1)))
    return TurnedScene(source, _display(albedo), mask, targets, probes, repeats)


def score_scene(relighter, spec, options, probe: str = PROBE, yaws=YAWS, size: int = 128, spp: int = 32
                ) -> tuple[dict, dict]:
    """Every measure above for one data-engine scene relit under `probe` at each of `yaws` (means over the pairs
    of yaws; the ceilings from a second render of the targets with other noise), and the images:
    (scores, {"scene", "relit", "albedo"})."""
    from relight_core.evaluation.harness import relight

    scene = render_turned(spec, probe, yaws, size, spp, again=True)
    again = scene.again
    results = [relight(relighter, scene.source[None], light[None], options) for light in scene.probes]
    relit, albedos = [r[0][0] for r in results], [r[1][0] for r in results]
    pairs = list(combinations(range(len(yaws)), 2))
    t, m = scene.targets, scene.mask
    scores = {
        "follow": [change_follow(t[a], t[b], relit[a], relit[b], m) for a, b in pairs],
        "follow_ceiling": [change_follow(t[a], t[b], again[a], again[b], m) for a, b in pairs],
        "follow_detail": [change_follow(t[a], t[b], relit[a], relit[b], m, DETAIL_SIGMA) for a, b in pairs],
        "follow_detail_ceiling": [change_follow(t[a], t[b], again[a], again[b], m, DETAIL_SIGMA) for a, b in pairs],
        "reach": [change_reach(t[a], t[b], relit[a], relit[b], m) for a, b in pairs],
        "shadow_agreement": [s for a, b in pairs
                             if (s := shadow_agreement(t[a], t[b], relit[a], relit[b], m)) is not None],
        "albedo_shading": [albedo_shading(albedo, scene.albedo, scene.source, m) for albedo in albedos],
    }
    row = {key: float(np.mean(values)) if values else None for key, values in scores.items()}
    return row, {"scene": scene, "relit": relit, "albedo": albedos}


def summary(rows: list[dict]) -> dict:
    """The mean of each measure over the scenes that have it."""
    return {key: float(np.mean(values)) if (values := [r[key] for r in rows if r[key] is not None]) else None
            for key in KEYS}


def measure(relighter, scenes: int, options, size: int = 128, probe: str = PROBE, yaws=YAWS, spp: int = 32,
            log: Callable[[str], None] | None = None) -> dict:
    """The first `scenes` held-out test scenes (data-engine seed 0) scored by `score_scene` at `size` px:
    {"scenes", "probe", "yaws", "size", "spp", "summary", "per_scene"}. Needs Mitsuba."""
    from relight_core.data.scenes import sample_scene

    rows = []
    for index in range(scenes):
        row, _ = score_scene(relighter, sample_scene(0, "test", index, 1), options, probe, yaws, size, spp)
        rows.append({"scene": index, **row})
        if log:
            log(f"  light follow [{index + 1}/{scenes}]: follow {row['follow']:.3f} (ceiling "
                f"{row['follow_ceiling']:.3f}), albedo shading {row['albedo_shading']:.3f}")
    return {"scenes": scenes, "probe": probe, "yaws": list(yaws), "size": size, "spp": spp,
            "summary": summary(rows), "per_scene": rows}
