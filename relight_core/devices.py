"""Which device runs a model, and how much memory it has free."""

from __future__ import annotations

import os

import torch

from relight_core.errors import InputError


def resolve_device(device: str | torch.device | None) -> torch.device:
    """The device to run on (None: cuda when available, else cpu); InputError for one that is absent or unknown."""
    if device is None or str(device).strip() == "":
        return torch.device("cuda" if torch.cuda.is_available() else "cpu")
    try:
        resolved = torch.device(str(device).strip())
    except (RuntimeError, TypeError, ValueError):
        raise InputError(f"'{device}' is not a device; use cpu, cuda or cuda:N.") from None
    if resolved.type == "cpu":
        return resolved
    if resolved.type == "cuda":
        if not torch.cuda.is_available():
            raise InputError(f"The device '{device}' was asked for, but this machine has no usable CUDA GPU; "
                             "run on cpu instead (--device cpu).")
        count = torch.cuda.device_count()
        if resolved.index is not None and resolved.index >= count:
            raise InputError(f"There is no GPU {device}: this machine has {count} (cuda:0 to cuda:{count - 1}).")
        return resolved
    if resolved.type == "mps" and torch.backends.mps.is_available():
        return resolved
    raise InputError(f"The device '{device}' is not available here; use cpu or cuda.")


def free_memory(device: torch.device) -> tuple[int, int | None]:
    """(free host bytes, free bytes on the device or None when the device is the host)."""
    host = None
    try:
        with open("/proc/meminfo") as f:
            info = {line.split(":")[0]: int(line.split()[1]) * 1024 for line in f if ":" in line}
        host = info.get("MemAvailable", info.get("MemFree"))
    except (OSError, ValueError, IndexError):
        pass
    if host is None:
        try:
            host = os.sysconf("SC_AVPHYS_PAGES") * os.sysconf("SC_PAGE_SIZE")
        except (OSError, ValueError, AttributeError):
            host = 8 << 30
    for limit_file, usage_file in (("/sys/fs/cgroup/memory.max", "/sys/fs/cgroup/memory.current"),
                                   ("/sys/fs/cgroup/memory/memory.limit_in_bytes",
                                    "/sys/fs/cgroup/memory/memory.usage_in_bytes")):
        try:  # a container's limit may be far below the machine's memory
            with open(limit_file) as f:
                limit = f.read().strip()
            with open(usage_file) as f:
                usage = int(f.read().strip())
            if limit.isdigit() and int(limit) < 1 << 60:
                host = min(host, max(0, int(limit) - usage))
            break
        except (OSError, ValueError):
            continue
    if device.type == "cuda":
        free, _ = torch.cuda.mem_get_info(device)
        return host, int(free)
    return host, None


def gb(size: int) -> str:
    return f"{size / 2**30:.1f} GB" if size < 10 * 2**30 else f"{size / 2**30:.0f} GB"
