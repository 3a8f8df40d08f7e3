"""The six test items with the lowest albedo PSNR in the shipped model's 400-item run, one row each: input | albedo
target | albedo | relit target | relit.   PYTHONPATH=. python runs/albedo-glass/worst.py OUT.png"""
import json, numpy as np, cv2, sys, torch
from pathlib import Path
from relight_core.evaluation.harness import RunOptions, load_items, relight
from relight_core.pipeline import Relighter
torch.set_num_threads(1)
C = Path.home() / ".cache/unirelight-studio"
per = json.load(open(C / "eval/shipped-S24-400/metrics.json"))["test"]["per_item"]
order = np.argsort([p["model"]["albedo"]["psnr"] for p in per])[:6]
items = load_items(C / "data", "test", 400)
r = Relighter.load("models/default", device="cpu", precision="fp32")
rows = []
for i in order:
    it = items[i]
    rel, alb, _ = relight(r, it.input, it.probe, RunOptions())
    print(per[i]["name"], per[i]["model"]["albedo"]["psnr"], per[i]["model"]["relit"]["psnr"])
    rows.append(np.concatenate([it.input[0], it.albedo[0], alb[0], it.target[0], rel[0]], 1))
cv2.imwrite(sys.argv[1], cv2.cvtColor((np.concatenate(rows, 0) * 255).astype(np.uint8), cv2.COLOR_RGB2BGR))
