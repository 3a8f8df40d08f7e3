"""The relit refiner's gain cell (`relit_gain`, trained at 4 px) at inference against its strength, on the
48 held-out test items `calibrate --split test --skip 16 --items 48` chooses on (relit PSNR, model precision):
    PYTHONPATH=. python runs/refiner-strength/cells.py MODEL [CELL ...]"""
import sys
from dataclasses import replace
from pathlib import Path

from relight_core.evaluation.harness import load_items, resized
from relight_core.pipeline import Relighter
from relight_core.training.calibrate import measure_strengths

relighter = Relighter.load(sys.argv[1])
items = [resized(item, relighter.spec.size, relighter.frame_multiple) for item in
         load_items(Path.home() / ".cache/unirelight-studio/data", "test", 48, spread=True, skip=16)]
config = relighter.relit_refiner.config
for cell in [int(c) for c in sys.argv[2:]] or [4, 6, 8]:
    relighter.relit_refiner.config = replace(config, relit_gain=cell)
    table = measure_strengths(relighter, items, grid=(0.6, 0.7, 0.8, 1.0))
    print(f"cell {cell}: " + "  ".join(f"s={s} relit {v['relit']:.3f}" for s, v in table.items()), flush=True)
