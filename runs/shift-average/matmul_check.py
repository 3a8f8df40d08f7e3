"""fp32 and bf16 matmul GFLOP/s (2048², 2 threads), the capability torch reports and the precision `auto` picks — run
it plain and under ATEN_CPU_CAPABILITY=avx2 ONEDNN_MAX_CPU_ISA=AVX2 MKL_ENABLE_INSTRUCTIONS=AVX2 (an AVX2-only CPU as
far as torch can tell; UNIRELIGHT_CACHE_DIR=/tmp/pc keeps the precision verdict apart):  PYTHONPATH=. python runs/shift-average/matmul_check.py"""
import time, torch
torch.set_num_threads(2)
print(torch.backends.cpu.get_cpu_capability())
from relight_core.precision import resolve_precision
print("auto ->", resolve_precision("auto", "cpu"))
for dt in (torch.float32, torch.bfloat16):
    a = torch.randn(2048, 2048).to(dt); b = torch.randn(2048, 2048).to(dt)
    torch.mm(a, b); best = 1e9
    for _ in range(3):
        s = time.perf_counter(); torch.mm(a, b); best = min(best, time.perf_counter() - s)
    print(dt, f"{2 * 2048**3 / best / 1e9:.1f} GFLOP/s")
