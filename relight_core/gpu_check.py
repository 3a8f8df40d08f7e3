"""`scripts/gpu_check.sh MODEL_DIR`: the released UniRelight weights on this GPU, timed, in one table.

The paper's runtime experiment (Appendix, "Runtime cost"): a 57-frame clip at 480×848, 35 denoising
steps, tokenizer encode and decode included — 445.5 s on one A100. The check runs that workload
(the bundled `examples/inputs/orbit.mp4` played forward and back to 57 frames, cropped to 16:9)
and one bundled image (`examples/inputs/objects.png`, same size), both under the bundled sunset
probe, through the `Relighter` the CLI and the studio use, after one untimed one-step warm-up.
Per workload it prints the network (DiT) calls, GPU seconds per call, total seconds, peak GPU
memory and the paper's number.

MODEL_DIR is a folder written by `python -m relight_core import-released` (any model folder or
preset works: `tiny` runs the whole check in seconds on any GPU, which is how the script itself is
tested). Before any weight is loaded it refuses, in one sentence, a machine without a CUDA GPU and
a GPU with less free memory than its estimate: the DiT's weights plus the `Relighter`'s own rule
for the activations of the tokenizer and the DiT (`Relighter.memory_estimate`).
"""

from __future__ import annotations

import argparse
import sys
import time
from dataclasses import dataclass

import numpy as np
import torch
import torch.nn.functional as F

from relight_core import lighting, media
from relight_core.checkpoint import REPO_ROOT, resolve_model
from relight_core.dit import JointDiT
from relight_core.errors import InputError
from relight_core.pipeline import Relighter, RelightRequest
from relight_core.precision import precision_name, resolve_precision
from relight_core.tokenizer import build_tokenizer

PAPER_SECONDS = 445.5    # one 57-frame clip at 480×848, 35 steps, encode + decode, one A100 (paper, Appendix)
PAPER_GPU = "A100"
PAPER_CALLS = 2 * 35 + 1  # the released sampler runs an unconditional pass even at guidance 0 (bench.py)
FRAMES, HEIGHT, WIDTH, STEPS = 57, 480, 848, 35
IMAGE = REPO_ROOT / "examples" / "inputs" / "objects.png"
VIDEO = REPO_ROOT / "examples" / "inputs" / "orbit.mp4"
PROBE = REPO_ROOT / "envmaps" / "sunset.exr"
NO_GPU = ("This machine has no CUDA GPU that PyTorch can use (torch.cuda.is_available() is False), so the GPU "
          "check cannot run; run it on a machine with an NVIDIA GPU and a CUDA build of torch.")


@dataclass(frozen=True)
class Workload:
    """One timed relight of a bundled input."""

    name: str
    frames: np.ndarray                   # [T,H,W,3] in [0,1], at the working size
    steps: int = STEPS
    paper_seconds: float | None = None   # the paper's time for this workload, where it reports one


@dataclass(frozen=True)
class Measurement:
    """What one workload cost."""

    workload: str
    frames: int
    height: int
    width: int
    steps: int
    calls: int                           # DiT forward calls
    network_seconds: float               # their summed time (GPU time, from CUDA events, on a GPU)
    seconds: float                       # the whole relight: lighting, encode, sampling, decode
    peak_bytes: int | None               # peak GPU memory allocated, weights included (None on a CPU)
    paper_seconds: float | None


@dataclass(frozen=True)
class Estimate:
    """GPU memory the check needs, known before any weight is loaded."""

    weights: int                         # the DiT's weights in its compute dtype
    network: int                         # activations of the tokenizer and the DiT (Relighter.memory_estimate)

    @property
    def total(self) -> int:
        return self.weights + self.network


def gib(size: int) -> str:
    """Bytes as GiB (MiB below one GiB, where a tiny model's numbers would read 0.0)."""
    return f"{size / 2**30:.1f} GiB" if size >= 2**30 else f"{size / 2**20:.0f} MiB"


def memory_estimate(model: str, dtype: torch.dtype, frames: int = FRAMES, height: int = HEIGHT,
                    width: int = WIDTH) -> Estimate:
    """The estimate for `frames` at height × width: parameters counted on the meta device × bytes of
    `dtype`, plus the Relighter's activation rule (the tokenizer is built on the CPU for its shape only)."""
    spec, directory = resolve_model(model)
    with torch.device("meta"):
        dit = JointDiT(spec.dit)
    tokenizer = build_tokenizer(spec.tokenizer, directory)
    _, network = Relighter(spec, dit, tokenizer, "cpu", precision="fp32").memory_estimate(frames, height, width)
    return Estimate(sum(p.numel() for p in dit.parameters()) * dtype.itemsize, network)


def refusal(estimate: Estimate, free: int, gpu: str) -> str | None:
    """The one sentence that stops the check when `estimate` exceeds the `free` bytes of `gpu`, else None."""
    if estimate.total <= free:
        return None
    return (f"The {gpu} has {gib(free)} free but this check needs about {gib(estimate.total)} "
            f"({gib(estimate.weights)} of weights and {gib(estimate.network)} to relight {FRAMES} frames at "
            f"{WIDTH}×{HEIGHT}), so it is too small; run the check on a GPU with more memory.")


def fit(frames: np.ndarray, height: int, width: int) -> np.ndarray:
    """Frames [T,h,w,3] centre-cropped to the aspect of height × width and resized to it."""
    _, h, w, _ = frames.shape
    crop_h, crop_w = min(h, round(w * height / width)), min(w, round(h * width / height))
    top, left = (h - crop_h) // 2, (w - crop_w) // 2
    x = torch.from_numpy(np.ascontiguousarray(frames[:, top:top + crop_h, left:left + crop_w])).permute(0, 3, 1, 2)
    x = F.interpolate(x, size=(height, width), mode="bilinear", antialias=True, align_corners=False)
    return x.clamp(0, 1).permute(0, 2, 3, 1).contiguous().numpy()                      # (T, H, W, 3)


def ping_pong(frames: np.ndarray, count: int) -> np.ndarray:
    """`count` frames of a clip played forward, backward, forward ... (no frame repeated at the turns)."""
    cycle = list(range(len(frames))) + list(range(len(frames) - 2, 0, -1))
    return frames[[cycle[i % len(cycle)] for i in range(count)]]


def bundled_workloads(frames: int = FRAMES, height: int = HEIGHT, width: int = WIDTH,
                      steps: int = STEPS) -> list[Workload]:
    """The bundled image and the bundled clip stretched to `frames`, both at height × width."""
    image = fit(media.load_image(IMAGE), height, width)
    video = fit(ping_pong(media.load_video(VIDEO).frames, frames), height, width)
    paper = PAPER_SECONDS if (frames, height, width, steps) == (FRAMES, HEIGHT, WIDTH, STEPS) else None
    return [Workload(f"image {IMAGE.name}", image, steps),
            Workload(f"video {VIDEO.name}, {frames} frames", video, steps, paper)]


class NetworkTimer:
    """Counts and times a module's forward calls; on a GPU with CUDA events (no synchronisation per call)."""

    def __init__(self, module: torch.nn.Module, device: torch.device):
        self.cuda = device.type == "cuda"
        self.spans: list[list] = []
        self.handles = [module.register_forward_pre_hook(self._start), module.register_forward_hook(self._stop)]

    def _mark(self):
        if not self.cuda:
            return time.perf_counter()
        event = torch.cuda.Event(enable_timing=True)
        event.record()
        return event

    def _start(self, module, args) -> None:
        self.spans.append([self._mark(), None])

    def _stop(self, module, args, output) -> None:
        self.spans[-1][1] = self._mark()

    @property
    def calls(self) -> int:
        return len(self.spans)

    def seconds(self) -> float:
        """Summed time of the calls so far."""
        if self.cuda:
            torch.cuda.synchronize()
            return sum(start.elapsed_time(stop) for start, stop in self.spans) / 1000
        return sum(stop - start for start, stop in self.spans)

    def close(self) -> None:
        for handle in self.handles:
            handle.remove()


def measure(relighter: Relighter, workload: Workload, probe: torch.Tensor) -> Measurement:
    """Relight `workload` once under `probe` and return what it cost."""
    cuda = relighter.device.type == "cuda"
    if cuda:
        torch.cuda.synchronize(relighter.device)
        torch.cuda.reset_peak_memory_stats(relighter.device)
    timer = NetworkTimer(relighter.dit, relighter.device)
    try:
        started = time.perf_counter()
        relighter.relight(RelightRequest(workload.frames, probe=probe, steps=workload.steps))
        if cuda:
            torch.cuda.synchronize(relighter.device)
        seconds = time.perf_counter() - started
        network_seconds = timer.seconds()
    finally:
        timer.close()
    frames, height, width = workload.frames.shape[:3]
    peak = torch.cuda.max_memory_allocated(relighter.device) if cuda else None
    return Measurement(workload.name, frames, height, width, workload.steps, timer.calls, network_seconds, seconds,
                       peak, workload.paper_seconds)


def format_table(title: str, rows: list[Measurement], estimate: Estimate | None = None) -> str:
    """The check's report: a title line, one Markdown table with a row per workload, and notes."""
    header = ("workload", "frames", "size", "steps", "network calls", "s / call", "total s", "peak GPU memory",
              f"paper ({PAPER_GPU})")
    cells = [(r.workload, str(r.frames), f"{r.width}×{r.height}", str(r.steps), str(r.calls),
              f"{r.network_seconds / max(r.calls, 1):.3f}", f"{r.seconds:.1f}",
              gib(r.peak_bytes) if r.peak_bytes is not None else "—",
              f"{r.paper_seconds:.1f} s" if r.paper_seconds is not None else "—") for r in rows]
    widths = [max(len(row[i]) for row in (header, *cells)) for i in range(len(header))]

    def line(row) -> str:  # the workload left-aligned, the numbers right-aligned
        padded = [c.ljust(w) if i == 0 else c.rjust(w) for i, (c, w) in enumerate(zip(row, widths))]
        return "| " + " | ".join(padded) + " |"

    rule = "|" + "|".join("-" * (w + 1) + ("-" if i == 0 else ":") for i, w in enumerate(widths)) + "|"
    notes = [f"network calls: ours are steps + 1 per chunk (no unconditional pass at guidance 0); the paper's "
             f"released sampler makes {PAPER_CALLS} per clip at {STEPS} steps."]
    if estimate is not None:
        notes.append(f"estimated before loading: {gib(estimate.total)} ({gib(estimate.weights)} weights + "
                     f"{gib(estimate.network)} activations).")
    return "\n".join([title, "", line(header), rule, *map(line, cells), "", *notes])


def run_check(model: str) -> str:
    """Run the whole check on this machine's GPU and return its report; InputError when it cannot run."""
    if not torch.cuda.is_available():
        raise InputError(NO_GPU)
    device = torch.device("cuda", torch.cuda.current_device())
    spec, _ = resolve_model(model)
    dtype = resolve_precision(spec.precision, device)
    estimate = memory_estimate(model, dtype)
    free, total = torch.cuda.mem_get_info(device)
    gpu = f"GPU {torch.cuda.get_device_name(device)}"
    sentence = refusal(estimate, free, gpu)
    if sentence is not None:
        raise InputError(sentence)
    started = time.perf_counter()
    relighter = Relighter.load(model, device=device)
    load_seconds = time.perf_counter() - started
    probe = lighting.load_probe(PROBE)
    workloads = bundled_workloads()
    relighter.relight(RelightRequest(workloads[0].frames, probe=probe, steps=1))   # warm-up: CUDA, kernels
    rows = [measure(relighter, workload, probe) for workload in workloads]
    params = sum(p.numel() for p in relighter.dit.parameters())
    size = f"{params / 1e9:.2f} B" if params >= 1e9 else f"{params / 1e6:.2f} M"
    title = (f"GPU check: {model} ({spec.name}, {size} parameters, {precision_name(dtype)}) on the "
             f"{gpu} ({gib(total)}), torch {torch.__version__}; loaded in {load_seconds:.1f} s")
    return format_table(title, rows, estimate)


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="scripts/gpu_check.sh",
                                     description="Time the released UniRelight weights on this GPU against the "
                                                 "paper's 445.5 s per 57-frame clip on an A100.")
    parser.add_argument("model", help="a model folder written by import-released (or a preset such as tiny)")
    args = parser.parse_args(argv)
    try:
        print(run_check(args.model), flush=True)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())
