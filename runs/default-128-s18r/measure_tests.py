"""The suite's test_default_model_beats_the_floor measurement for a model folder (its docstring's numbers):
PYTHONPATH=. python runs/default-128-s18r/measure_tests.py MODEL_DIR"""
import sys
import tempfile
from pathlib import Path

from relight_core.data.generate import RenderConfig, render_dataset
from relight_core.evaluation.harness import RunOptions, load_items, mean_metrics, measure_item
from relight_core.pipeline import Relighter

relighter = Relighter.load(sys.argv[1], device="cpu")
with tempfile.TemporaryDirectory() as tmp:
    render_dataset(RenderConfig(out=Path(tmp), scenes=2, frames=1, size=max(relighter.spec.size, 128), spp=16,
                                workers=1, split="test"), progress=False)
    records = [measure_item(relighter, item, RunOptions(), margin=False)[0] for item in load_items(Path(tmp), "test")]
for clip in ("relit", "albedo"):
    print(clip, *(f"{kind} {mean_metrics(records, kind, clip, 'psnr'):.2f}" for kind in ("model", "floor")))
