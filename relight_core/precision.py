"""Which floating-point precision the networks compute in: chosen by the hardware, never by a file.

`resolve_precision(name, device)` is the one rule, used by inference (`Relighter`), the benchmark and
training alike:

* `fp32`, `bf16`, `fp16` are taken as asked (fp16 only on a CUDA GPU);
* `auto` on a CUDA GPU is bf16 where the GPU supports it, else fp32;
* `auto` on a CPU is bf16 only where a bf16 matmul is *measured* faster than an fp32 one. On x86
  CPUs without AVX-512 (`torch.backends.cpu.get_cpu_capability()` reports AVX2 or less) there is no
  native bf16 — it runs ~80× slower than fp32 — so fp32 is picked at once, without measuring. Other
  CPUs run a small one-off matmul micro-benchmark (well under a second; the dtypes take turns, each keeping its
  best, so a moment of other load does not decide), whose verdict is cached in
  `~/.cache/unirelight-studio/precision.json` keyed by CPU model, torch version, thread count and the number of
  turns.

The dtype weights are *stored* in (bf16 halves a shipped file) never decides the compute dtype.
"""

from __future__ import annotations

import json
import os
import platform
import time
from contextlib import nullcontext
from pathlib import Path

import torch

from relight_core.arguments import PRECISIONS
from relight_core.errors import InputError

DTYPES = {"fp32": torch.float32, "bf16": torch.bfloat16, "fp16": torch.float16}
CACHE_FILE = "precision.json"
BF16_MARGIN = 1.2      # bf16 must beat fp32 by this factor: autocast adds casts the matmul does not see
MEASURE_SIZE = 512     # matmul side of the micro-benchmark
MEASURE_BUDGET_S = 0.5  # per dtype, after one warm-up call

_verdicts: dict[str, bool] = {}  # this process's answers, by cache key


def precision_name(dtype: torch.dtype) -> str:
    """torch.float32 → "fp32" (the inverse of DTYPES)."""
    for name, value in DTYPES.items():
        if value == dtype:
            return name
    raise ValueError(f"no precision name for {dtype}")


def check_precision(name: str) -> str:
    """`name` when it is one of PRECISIONS, else InputError."""
    if name not in PRECISIONS:
        raise InputError(f"Unknown precision {name!r}; choose one of {', '.join(PRECISIONS)}.")
    return name


def resolve_precision(name: str = "auto", device: str | torch.device = "cpu") -> torch.dtype:
    """The dtype the networks compute in for precision `name` on `device` (see the module docstring)."""
    name = check_precision(name)
    device = torch.device(device)
    if name == "fp16" and device.type != "cuda":
        raise InputError(f"fp16 runs only on a CUDA GPU, not on {device.type}; "
                         "use --precision auto, fp32 or bf16 here.")
    if name != "auto":
        return DTYPES[name]
    if device.type == "cuda":
        return torch.bfloat16 if torch.cuda.is_bf16_supported() else torch.float32
    if device.type == "cpu":
        return torch.bfloat16 if cpu_prefers_bf16() else torch.float32
    return torch.float32


def cpu_capability() -> str:
    """torch's CPU kernel capability: "AVX2", "AVX512", "DEFAULT", "SVE256", ..."""
    return torch.backends.cpu.get_cpu_capability()


def cpu_may_have_fast_bf16() -> bool:
    """False where bf16 is certainly emulated: an x86 CPU whose kernels stop at AVX2."""
    machine = platform.machine().lower()
    if machine in ("x86_64", "amd64", "i386", "i686", "x86"):
        capability = cpu_capability().upper()
        return "AVX512" in capability or "AMX" in capability
    return True  # ARM and others: measure (some have bf16 matrix instructions, many do not)


def cpu_model() -> str:
    """The CPU's model name (from /proc/cpuinfo on Linux)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.lower().startswith(("model name", "hardware", "cpu model")):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown cpu"


def cache_key() -> str:
    """What the measured verdict depends on: the CPU, torch, the thread count and how it was measured (a verdict
    of the one-turn-each measurement before `MEASURE_ROUNDS` is measured again)."""
    return (f"{cpu_model()} | {cpu_capability()} | torch {torch.__version__} | {torch.get_num_threads()} threads"
            f" | {MEASURE_ROUNDS} turns")


def cache_path() -> Path:
    """~/.cache/unirelight-studio/precision.json ($UNIRELIGHT_CACHE_DIR or $XDG_CACHE_HOME move it)."""
    root = os.environ.get("UNIRELIGHT_CACHE_DIR")
    if root:
        return Path(root) / CACHE_FILE
    base = os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache"
    return Path(base) / "unirelight-studio" / CACHE_FILE


def matmul_gflops(dtype: torch.dtype, n: int = MEASURE_SIZE, budget_s: float = MEASURE_BUDGET_S,
                  max_calls: int = 5) -> float:
    """Fastest GFLOP/s of an n×n CPU matmul: one warm-up call, then calls until `budget_s` is spent."""
    a = torch.randn(n, n).to(dtype)
    b = torch.randn(n, n).to(dtype)
    torch.mm(a, b)
    best = float("inf")
    spent = 0.0
    for _ in range(max_calls):
        start = time.perf_counter()
        torch.mm(a, b)
        seconds = time.perf_counter() - start
        best = min(best, seconds)
        spent += seconds
        if spent > budget_s:
            break
    return 2 * n ** 3 / max(best, 1e-9) / 1e9


MEASURE_ROUNDS = 3     # the two dtypes take turns this many times; each keeps its best


def measure_cpu_matmul(rounds: int = MEASURE_ROUNDS) -> dict[str, float]:
    """{"fp32": GFLOP/s, "bf16": GFLOP/s} of the micro-benchmark on this CPU: the dtypes take turns for
    `rounds` rounds and each keeps its best, so a burst of other work during one dtype's turn does not decide
    the verdict that gets cached (measured once on a 2-core AMD EPYC with AVX512-BF16 while a render held both
    cores: one turn each gave fp32 187.7 and bf16 33.9 GFLOP/s, and fp32 was cached for 2 threads; idle, bf16
    is 2.2× fp32 there: 436 against 197)."""
    best = {"fp32": 0.0, "bf16": 0.0}
    for _ in range(rounds):
        for name in best:
            best[name] = max(best[name], matmul_gflops(DTYPES[name], budget_s=MEASURE_BUDGET_S / rounds))
    return best


def cpu_prefers_bf16() -> bool:
    """Whether bf16 compute is faster than fp32 on this CPU: by capability, else measured once and cached."""
    if not cpu_may_have_fast_bf16():
        return False
    key = cache_key()
    if key in _verdicts:
        return _verdicts[key]
    path = cache_path()
    try:
        stored = json.loads(path.read_text())
        entry = stored.get(key) if isinstance(stored, dict) else None
    except (OSError, ValueError):
        stored, entry = {}, None
    if isinstance(entry, dict) and isinstance(entry.get("bf16_faster"), bool):
        _verdicts[key] = entry["bf16_faster"]
        return entry["bf16_faster"]
    measured = measure_cpu_matmul()
    verdict = measured["bf16"] > BF16_MARGIN * measured["fp32"]
    _verdicts[key] = verdict
    stored = stored if isinstance(stored, dict) else {}
    stored[key] = {"bf16_faster": verdict, "gflops": {k: round(v, 1) for k, v in measured.items()},
                   "matmul": MEASURE_SIZE, "measured": time.strftime("%Y-%m-%d %H:%M:%S")}
    try:  # a read-only home only costs a re-measurement in the next process
        path.parent.mkdir(parents=True, exist_ok=True)
        partial = path.with_name(f".{path.name}.{os.getpid()}")
        partial.write_text(json.dumps(stored, indent=1))
        os.replace(partial, path)
    except OSError:
        pass
    return verdict


def autocast(dtype: torch.dtype, device: str | torch.device = "cpu"):
    """An autocast context for a reduced precision, a no-op for fp32."""
    if dtype == torch.float32:
        return nullcontext()
    return torch.autocast(torch.device(device).type, dtype=dtype)
