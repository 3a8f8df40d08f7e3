import time, numpy as np, torch
from relight_core.pipeline import Relighter, RelightRequest
from relight_core.lighting import load_probe
torch.set_num_threads(2)
frames = np.random.default_rng(0).random((1, 128, 128, 3)).astype(np.float32)
probe = load_probe("envmaps/sunset.exr")
for prec in ("auto", "fp32"):
    r = Relighter.load("default", device="cpu", precision=prec)
    ref = r.refiner
    for name, refiner in (("with", ref), ("without", None)):
        r.refiner = refiner
        r.relight(RelightRequest(frames, probe=probe))
        t = []
        for _ in range(10):
            s = time.perf_counter(); r.relight(RelightRequest(frames, probe=probe)); t.append(time.perf_counter() - s)
        print(prec, r.precision, name, f"{np.median(t):.3f} s", flush=True)
