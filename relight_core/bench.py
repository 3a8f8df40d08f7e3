"""`python -m relight_core bench`: DiT throughput against this machine's matmul peak.

Prints, for the `tiny` and `small` presets at 256×256 (one latent frame) and 256×256×17 frames,
the DiT forward time and the achieved GFLOP/s (matmul FLOPs counted by torch's FlopCounterMode,
plus attention's 4·L²·D a block where the counter misses it), in the precision the Relighter would
use here (`--precision`, default auto: see precision.py), as a fraction of the measured matmul peak
*of that precision*; both the fp32 and the bf16 matmul peak (bf16 at a smaller size on a CPU
where it is slow, so that the quick bench stays under a minute anywhere); the denoiser evaluations
per relight of our sampler and of the released one; the 7B preset's parameter count; peak
resident memory; and what a user waits for (`latency`): model load and warm-up, the first streamed
preview, a whole relight at the model's size and at 256 px (guided full-resolution output), the
estimate shown before it against the measured time, and one light-preview render.
"""

from __future__ import annotations

import json
import resource
import time
from pathlib import Path

import torch
from torch.utils.flop_counter import FlopCounterMode

from relight_core.checkpoint import MODEL_PRESETS
from relight_core.diffusion import SAMPLERS, get_sigmas_karras
from relight_core.dit import CHANNELS, JointDiT, param_count
from relight_core.precision import autocast, matmul_gflops, precision_name, resolve_precision

RELEASED_STEPS = 35
PEAK_SIZE = 2048          # matmul side of the peak (1024 for --quick); for bf16 ...
MIN_PEAK_SIZE = 256       # ... halved down to this while one call would take longer than
PEAK_CALL_BUDGET_S = 0.5  # this many seconds (bf16 on a CPU without native bf16: ~1 GFLOP/s)


def _timeit(fn, repeats: int, warmup: int = 2) -> float:
    """Fastest seconds of `fn()` over `repeats` calls after `warmup` calls.

    The fastest run is the least disturbed one on a shared 2-core machine; both the matmul peak and
    the DiT are timed this way, so their ratio compares like with like.
    """
    for _ in range(warmup):
        fn()
    times = []
    for _ in range(repeats):
        start = time.perf_counter()
        fn()
        times.append(time.perf_counter() - start)
    return min(times)


def matmul_peak_gflops(dtype: torch.dtype, n: int = 2048, repeats: int = 10) -> float:
    """Achieved GFLOP/s of an n×n matmul: the practical peak the DiT is measured against."""
    a = torch.randn(n, n, dtype=dtype)
    b = torch.randn(n, n, dtype=dtype)
    seconds = _timeit(lambda: torch.mm(a, b), repeats)
    return 2 * n ** 3 / seconds / 1e9


def peak_size(dtype: torch.dtype, n: int = PEAK_SIZE, budget_s: float = PEAK_CALL_BUDGET_S) -> int:
    """The matmul side to measure `dtype`'s peak at: `n`, halved while one call would exceed `budget_s`
    (judged from a 256² probe)."""
    rate = matmul_gflops(dtype, MIN_PEAK_SIZE, budget_s=0.05, max_calls=2) * 1e9
    while n > MIN_PEAK_SIZE and 2 * n ** 3 / rate > budget_s:
        n //= 2
    return n


def count_evaluations(steps: int, guidance: float) -> int:
    """Denoiser calls of one relight with our res2ab sampler (a toy denoiser counts them)."""
    calls = 0

    def denoiser(x, sigma, **_):
        nonlocal calls
        calls += 1 if guidance == 0 else 2
        return torch.zeros_like(x)

    SAMPLERS["res2ab"](denoiser, torch.zeros(1), get_sigmas_karras(steps))
    return calls


def attention_flops(depth: int, width: int, tokens: int) -> int:
    """FLOPs of full self-attention over `tokens` in every block: 2·L²·D for Q·Kᵀ, 2·L²·D for P·V."""
    return depth * 4 * tokens * tokens * width


def counter_sees_attention(dtype: torch.dtype = torch.float32) -> bool:
    """Whether FlopCounterMode counts scaled_dot_product_attention on this device and build."""
    q = torch.randn(1, 2, 64, 32, dtype=dtype)
    with torch.no_grad(), FlopCounterMode(display=False) as counter:
        torch.nn.functional.scaled_dot_product_attention(q, q, q)
    return counter.get_total_flops() > 0


def dit_forward(preset: str, frames: int, size: int = 256, repeats: int = 5,
                dtype: torch.dtype = torch.float32) -> dict:
    """Time one forward of a preset's DiT on a [input | relit | albedo] clip, as the Relighter runs it
    in `dtype`: weights in `dtype`, under autocast unless fp32."""
    spec = MODEL_PRESETS[preset]
    model = JointDiT(spec.dit).eval().to(dtype)
    t = 1 + (frames - 1) // 8
    h = w = size // 8
    x = torch.randn(1, CHANNELS["padding_mask"].stop, 3 * t, h, w)
    c_noise = torch.zeros(1)

    def forward():
        with torch.no_grad(), autocast(dtype):
            model(x, c_noise)

    with FlopCounterMode(display=False) as counter:
        forward()
    tokens = 3 * t * (h // spec.dit.patch_spatial) * (w // spec.dit.patch_spatial)
    flops = counter.get_total_flops()
    if not counter_sees_attention(dtype):  # torch 2.13 records 0 for CPU flash attention: add Q·Kᵀ and P·V
        flops += attention_flops(spec.dit.depth, spec.dit.width, tokens)
    seconds = _timeit(forward, repeats)
    return {"preset": preset, "frames": frames, "size": size, "tokens": tokens, "precision": precision_name(dtype),
            "params_M": round(sum(p.numel() for p in model.parameters()) / 1e6, 2),
            "seconds": round(seconds, 4), "gflop": round(flops / 1e9, 2),
            "gflops_per_s": round(flops / seconds / 1e9, 1)}


def latency(model: str = "default", precision: str = "auto", preview: bool = True) -> dict:
    """Seconds a user waits, on this machine, for `model` (module docstring)."""
    import numpy as np

    from relight_core import upsample
    from relight_core.media import resize_frames
    from relight_core.pipeline import Progress, Relighter, RelightRequest

    out: dict = {"model": model}
    started = time.perf_counter()
    relighter = Relighter.load(model, device="cpu", precision=precision)
    out["load_s"] = time.perf_counter() - started
    out["warm_up_s"] = relighter.warm_up()
    size = relighter.spec.size // relighter.frame_multiple * relighter.frame_multiple
    rng = np.random.default_rng(0)
    probe = torch.rand(64, 128, 3, generator=torch.Generator().manual_seed(0)) * 2
    frames = rng.random((1, size, size, 3), dtype=np.float32)
    out["size"] = size
    out["estimate_s"] = relighter.estimate_seconds(1, size, size)
    started = time.perf_counter()
    first = None
    for event in relighter.run(RelightRequest(frames, probe=probe, rotation=30.0)):
        if first is None and isinstance(event, Progress):
            first = time.perf_counter() - started
    out["first_preview_s"], out["relight_s"] = first, time.perf_counter() - started
    full = rng.random((1, 256, 256, 3), dtype=np.float32)
    started = time.perf_counter()
    small = resize_frames(full, size, multiple=relighter.frame_multiple)
    result = relighter.relight(RelightRequest(small, probe=probe, rotation=60.0))
    upsample.guided_ratio_upsample(full, small, result.relit)
    upsample.guided_ratio_upsample(full, small, result.albedo)
    out["relight_256_s"] = time.perf_counter() - started
    if preview:
        from relight_core.preview import render_preview

        render_preview(probe, 0.0)  # the first render opens the GL context
        times = []
        for angle in (10.0, 20.0, 30.0):
            started = time.perf_counter()
            render_preview(probe, angle)
            times.append(time.perf_counter() - started)
        out["light_preview_s"] = sorted(times)[1]
    return {k: round(v, 3) if isinstance(v, float) else v for k, v in out.items()}


def run_bench(quick: bool = False, out: Path | None = None, precision: str = "auto") -> dict:
    """Run every measurement, print a table and return the numbers.

    The DiT runs in `precision` resolved for this CPU (auto: see precision.py) and is compared with
    that precision's matmul peak; both peaks are measured either way.
    """
    dtype = resolve_precision(precision, "cpu")
    used = precision_name(dtype)
    torch.manual_seed(0)
    peaks, sizes = {}, {}
    for name, peak_dtype in (("fp32", torch.float32), ("bf16", torch.bfloat16)):
        full = 1024 if quick else PEAK_SIZE
        # fp32 is native everywhere; bf16 is sized down where it is emulated (~1 GFLOP/s)
        sizes[name] = full if peak_dtype == torch.float32 else peak_size(peak_dtype, full)
        repeats = 3 if quick or sizes[name] < PEAK_SIZE // 2 else 10
        peaks[name] = matmul_peak_gflops(peak_dtype, sizes[name], repeats)
    print(f"matmul peak (measured): fp32 {peaks['fp32']:.0f} GFLOP/s ({sizes['fp32']}²), "
          f"bf16 {peaks['bf16']:.1f} GFLOP/s ({sizes['bf16']}²), {torch.get_num_threads()} threads; "
          f"the DiT runs in {used} (--precision {precision})")
    rows = []
    presets = ["tiny"] if quick else ["tiny", "small"]
    for preset in presets:
        for frames in (1, 17):
            row = dit_forward(preset, frames, repeats=2 if quick else 5, dtype=dtype)
            row["vs_peak"] = round(row["gflops_per_s"] / peaks[used], 3)
            rows.append(row)
            print(f"DiT {preset:>5} {row['params_M']:7.2f}M  256×256×{frames:<2} {row['tokens']:5d} tokens  "
                  f"{row['seconds'] * 1e3:8.1f} ms  {row['gflop']:8.2f} GFLOP  {row['gflops_per_s']:7.1f} GFLOP/s"
                  f"  = {100 * row['vs_peak']:.0f}% of {used} peak")
    ours = count_evaluations(RELEASED_STEPS, guidance=0.0)
    released = 2 * RELEASED_STEPS + 1  # the released sampler also runs the unconditional pass at guidance 0
    print(f"denoiser evaluations per relight ({RELEASED_STEPS} steps, guidance 0): ours {ours}, "
          f"released sampler {released}")
    params_7b = param_count(MODEL_PRESETS["unirelight-7b"].dit)
    print(f"unirelight-7b preset: {params_7b / 1e9:.3f} B parameters (meta device)")
    waits = latency("tiny" if quick else "default", precision, preview=not quick)
    print(f"latency ({waits['model']}, {waits['size']} px): load {waits['load_s']:.2f} s, warm-up "
          f"{waits['warm_up_s']:.2f} s, first preview {waits['first_preview_s']:.2f} s, relight "
          f"{waits['relight_s']:.2f} s (estimated {waits['estimate_s']:.2f} s), 256 px with full-resolution "
          f"output {waits['relight_256_s']:.2f} s" +
          (f", light preview {waits['light_preview_s']:.2f} s" if "light_preview_s" in waits else ""))
    peak_rss_mb = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024
    print(f"peak resident memory: {peak_rss_mb:.0f} MB")
    numbers = {"latency": waits, "matmul_peak_gflops": {k: round(v, 1) for k, v in peaks.items()}, "matmul_size": sizes,
               "precision": used, "precision_asked": precision, "threads": torch.get_num_threads(),
               "dit": rows, "evaluations": {"ours": ours, "released": released},
               "unirelight_7b_params": params_7b, "peak_rss_mb": round(peak_rss_mb)}
    if out is not None:
        Path(out).write_text(json.dumps(numbers, indent=2))
    return numbers
