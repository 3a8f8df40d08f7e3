"""How much a JPEG-92 input costs the shipped model: the first N test items relit from their rendered PNG input and
from the same input as a training pack holds it (`training.pack`, JPEG quality 92, 4:4:4), scored against the PNG
target by the protocol (fp32/bf16 by the model's "auto").

    PYTHONPATH=. python runs/dit-top/jpeg_inputs.py ~/.cache/unirelight-studio 8 > runs/dit-top/jpeg-inputs-8.txt
(packs the first N test scenes both ways into CACHE/jpeg-check/)
"""
import sys
from pathlib import Path

import numpy as np
import torch

from relight_core.evaluation.harness import load_items
from relight_core.evaluation.metrics import protocol_psnr
from relight_core.pipeline import Relighter, RelightRequest
from relight_core.training.pack import load_packs, write_pack
from relight_core.training.refine import _hwc

cache, n = Path(sys.argv[1]).expanduser(), int(sys.argv[2])
torch.set_num_threads(2)
folder = cache / "jpeg-check"
packs = {}
for name, lossless in (("jpeg", False), ("png", True)):
    write_pack(cache / "data", "test", folder / f"{name}.npz", limit=n, lossless=lossless)
    packs[name] = load_packs([folder / f"{name}.npz"])
relighter = Relighter.load("default")
rows = []
for item in load_items(cache / "data", "test", 2 * n):
    scene, (a, b) = int(item.name.split()[0].split("_")[1]), item.name.split()[1].split("→")
    scores = {}
    for name, pack in packs.items():
        frames = _hwc(pack["rgb"][scene:scene + 1, int(a)])
        result = relighter.relight(RelightRequest(frames, mode="relight", camera_probe=item.probe, seed=0))
        scores[name] = protocol_psnr(result.relit, item.target, item.mask)
    assert np.allclose(_hwc(packs["png"]["rgb"][scene:scene + 1, int(a)]), item.input, atol=1e-6)   # the PNG pack: exact
    rows.append((scores["png"], scores["jpeg"]))
    print(f"{item.name}: relit from the PNG input {scores['png']:.2f}, from its JPEG-92 {scores['jpeg']:.2f}")
png, jpeg = np.array(rows).T
print(f"{len(rows)} items: PNG {png.mean():.3f}, JPEG {jpeg.mean():.3f}, PNG − JPEG {np.mean(png - jpeg):+.3f} ± "
      f"{np.std(png - jpeg, ddof=1) / np.sqrt(len(rows)):.3f} (± over items)")
