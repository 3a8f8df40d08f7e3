"""Do the shadows move when the probe turns, and does the albedo keep the input's shadows? (issue 7's visible
criteria, measured with relight_core/evaluation/light_follow.py: `evaluate --follow-scenes N` reports the same).
Held-out test scenes (seed 0) are rendered under their own first probe (the input) and under the held-out sunset
probe (a low sun: long, hard shadows) turned to four world yaws; the model relights the input under each (fp32, its
own size, results at 128 px), and each pair of yaws is scored: follow (and its ceiling: a second render of the truth
with other noise), follow of the detail (the changes less their blur, σ 3 px), reach, shadow agreement; and the
albedo's shading slope (1 = the input's shading kept, 0 = none). Writes summary.json and scenes.png (three scenes).
    PYTHONPATH=. python runs/shadow-follow/probe.py SCENES MODEL OUT_DIR
"""
import json
import os
import sys
from pathlib import Path

import numpy as np
import torch

from relight_core.data.render import init_mitsuba
from relight_core.data.scenes import sample_scene
from relight_core.evaluation import light_follow as lf
from relight_core.evaluation.harness import RunOptions
from relight_core.pipeline import Relighter

torch.set_num_threads(int(os.environ.get("T", "2")))
scenes, model, out = int(sys.argv[1]), sys.argv[2], Path(sys.argv[3])
out.mkdir(parents=True, exist_ok=True)
PROBE = os.environ.get("PROBE", lf.PROBE)
init_mitsuba(threads=2)
relighter = Relighter.load(model, device="cpu", precision="fp32")
rows, pictures = [], []
for index in range(scenes):
    spec = sample_scene(0, "test", index, 1)
    row, images = lf.score_scene(relighter, spec, RunOptions(), PROBE)
    rows.append({"scene": index, "objects": len(spec.objects), **row})
    print(json.dumps(rows[-1]), flush=True)
    if index < 3:
        scene, relit, albedos = images["scene"], images["relit"], images["albedo"]
        t = scene.targets
        pictures.append(np.concatenate([np.concatenate([scene.source, scene.albedo, albedos[0], albedos[2]], 1)]
                                       + [np.concatenate([t[k], relit[k], t[k + 1], relit[k + 1]], 1) for k in (0, 2)], 0))

summary = lf.summary(rows)
summary.update(scenes=scenes, model=model, probe=PROBE, yaws=list(lf.YAWS))
print("summary", json.dumps(summary))
(out / "summary.json").write_text(json.dumps({"summary": summary, "scenes": rows}, indent=1))
if pictures:
    from PIL import Image

    grid = np.concatenate(pictures, 0)
    Image.fromarray((np.clip(grid, 0, 1) * 255 + 0.5).astype(np.uint8)).save(out / "scenes.png")
