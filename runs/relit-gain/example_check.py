"""The suite's example-image check (tests/test_default_model.py) for model folders, with what the relit
refiner does to the dark pixels, and a picture of the results:
    PYTHONPATH=. python runs/relit-gain/example_check.py OUT.png MODEL [MODEL ...]
Per model and bundled probe: the log-edge correlation of the result with the input (the test asks
> 0.8 under sunset, > 0.25 under studio) and its mean; against the first model, the mean change where
that model's result is below 0.08. The picture: a row per model — the input, then sunset, studio (×3),
city and courtyard."""
import sys
from pathlib import Path

import numpy as np
from PIL import Image

from relight_core import media
from relight_core.lighting import load_probe
from relight_core.pipeline import Relighter, RelightRequest

sys.path.insert(0, str(Path(__file__).resolve().parents[2] / "tests"))
from test_default_model import _log_edges  # noqa: E402

frames = media.resize_frames(media.load_media(Path("examples/inputs/objects.png")).frames, 128)
probes = {name: load_probe(Path(f"envmaps/{name}.exr")) for name in ("sunset", "studio", "city", "courtyard", "interior")}
first, rows = None, []
for model in sys.argv[2:]:
    relighter = Relighter.load(model, device="cpu")
    results = {name: relighter.relight(RelightRequest(frames, probe=probe)).relit for name, probe in probes.items()}
    first = first or results
    line = []
    for name, relit in results.items():
        corr = np.corrcoef(_log_edges(relit), _log_edges(frames))[0, 1]
        dark = first[name].mean(-1) < 0.08
        lift = (relit - first[name]).mean(-1)[dark].mean() if dark.any() else 0.0
        line.append(f"{name} {corr:+.3f} (mean {relit.mean():.3f}, below 0.08 {lift:+.3f})")
    print(model, "|", " | ".join(line), flush=True)
    rows.append(np.concatenate([frames[0], *(np.clip(results[n][0] * k, 0, 1) for n, k in
                                             (("sunset", 1), ("studio", 3), ("city", 1), ("courtyard", 1)))], 1))
Image.fromarray((np.concatenate(rows, 0) * 255).round().astype(np.uint8)).save(sys.argv[1])
