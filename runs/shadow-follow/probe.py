"""Do the shadows move when the probe turns, and does the albedo keep the input's shadows? (issue 7's visible
criteria, measured with relight_core/evaluation/light_follow.py). Held-out test scenes (seed 0) are rendered under
their own first probe (the input) and under the held-out sunset probe (a low sun: long, hard shadows) turned to
four world yaws; the model relights the input under each (fp32, its own size, results at 128 px), and each pair of
yaws is scored: follow (and its ceiling: a second render of the truth with other noise), follow of the detail (the
changes less their blur, σ 3 px), reach, shadow agreement; and the albedo's shading slope (1 = the input's shading
kept, 0 = none).
    PYTHONPATH=. python runs/shadow-follow/probe.py SCENES MODEL OUT_DIR
"""
import json
import os
import sys
from itertools import combinations
from pathlib import Path

import numpy as np
import torch

from relight_core.data.render import init_mitsuba
from relight_core.data.scenes import sample_scene
from relight_core.evaluation import light_follow as lf
from relight_core.evaluation.harness import RunOptions, relight
from relight_core.pipeline import Relighter

torch.set_num_threads(int(os.environ.get("T", "2")))
scenes, model, out = int(sys.argv[1]), sys.argv[2], Path(sys.argv[3])
out.mkdir(parents=True, exist_ok=True)
YAWS = (0.0, 90.0, 180.0, 270.0)
PROBE = os.environ.get("PROBE", "file:sunset")
DETAIL_SIGMA = 3.0
KEYS = ("follow", "follow_ceiling", "follow_detail", "follow_detail_ceiling", "reach", "shadow_agreement",
        "albedo_shading")
init_mitsuba(threads=2)
relighter = Relighter.load(model, device="cpu", precision="fp32")
rows, pictures = [], []
for index in range(scenes):
    spec = sample_scene(0, "test", index, 1)
    scene = lf.render_turned(spec, PROBE, YAWS)
    again = lf.render_turned(spec, PROBE, YAWS, noise_seed=1).targets  # other noise: the ceilings
    results = [relight(relighter, scene.source[None], probe[None], RunOptions()) for probe in scene.probes]
    relit, albedos = [r[0][0] for r in results], [r[1][0] for r in results]
    pairs = list(combinations(range(len(YAWS)), 2))
    t, m = scene.targets, scene.mask
    scores = {
        "follow": [lf.change_follow(t[a], t[b], relit[a], relit[b], m) for a, b in pairs],
        "follow_ceiling": [lf.change_follow(t[a], t[b], again[a], again[b], m) for a, b in pairs],
        "follow_detail": [lf.change_follow(t[a], t[b], relit[a], relit[b], m, DETAIL_SIGMA) for a, b in pairs],
        "follow_detail_ceiling": [lf.change_follow(t[a], t[b], again[a], again[b], m, DETAIL_SIGMA) for a, b in pairs],
        "reach": [lf.change_reach(t[a], t[b], relit[a], relit[b], m) for a, b in pairs],
        "shadow_agreement": [s for a, b in pairs
                             if (s := lf.shadow_agreement(t[a], t[b], relit[a], relit[b], m)) is not None],
        "albedo_shading": [lf.albedo_shading(alb, scene.albedo, scene.source, m) for alb in albedos],
    }
    row = {"scene": index, "objects": len(spec.objects),
           **{key: float(np.mean(v)) if v else None for key, v in scores.items()}}
    rows.append(row)
    print(json.dumps(row), flush=True)
    if index < 3:
        pictures.append(np.concatenate([np.concatenate([scene.source, scene.albedo, albedos[0], albedos[2]], 1)]
                                       + [np.concatenate([t[k], relit[k], t[k + 1], relit[k + 1]], 1) for k in (0, 2)], 0))

summary = {key: float(np.mean([r[key] for r in rows if r[key] is not None])) for key in KEYS}
summary.update(scenes=scenes, model=model, probe=PROBE, yaws=list(YAWS))
print("summary", json.dumps(summary))
(out / "summary.json").write_text(json.dumps({"summary": summary, "scenes": rows}, indent=1))
if pictures:
    from PIL import Image

    grid = np.concatenate(pictures, 0)
    Image.fromarray((np.clip(grid, 0, 1) * 255 + 0.5).astype(np.uint8)).save(out / "scenes.png")
