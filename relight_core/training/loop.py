"""What every training run shares: per-step randomness, EMA, resumable checkpoints, the JSONL log.

A run lives in one folder:

    <run>/log.jsonl                    one JSON object per logged step (committed)
    <run>/ckpt/latest.json             {"step": N, "folder": "step_000N"}, written last (atomic)
    <run>/ckpt/step_000N/*.safetensors module weights (model, EMA)
    <run>/ckpt/step_000N/optimizer.pt  optimizer state, read back with weights_only=True

Every random draw of step N comes from `step_generator(seed, N)`, so a run resumed from a
checkpoint draws exactly what the uninterrupted run would have drawn.
"""

from __future__ import annotations

import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file
from torch import nn

CHECKPOINT_DIR = "ckpt"
LATEST = "latest.json"
LOG_FILE = "log.jsonl"


def step_generator(seed: int, step: int, stream: int = 0) -> torch.Generator:
    """A CPU generator that depends only on (seed, step, stream)."""
    state = np.random.SeedSequence([seed, step, stream]).generate_state(1, dtype=np.uint64)[0]
    return torch.Generator().manual_seed(int(state))


def make_optimizer(model: nn.Module, lr: float, betas: tuple[float, float], weight_decay: float,
                   eps: float = 1e-8) -> torch.optim.AdamW:
    """AdamW with weight decay on matrices only (norm scales and biases are not decayed)."""
    decay = [p for p in model.parameters() if p.requires_grad and p.ndim >= 2]
    no_decay = [p for p in model.parameters() if p.requires_grad and p.ndim < 2]
    groups = [{"params": decay, "weight_decay": weight_decay}, {"params": no_decay, "weight_decay": 0.0}]
    return torch.optim.AdamW(groups, lr=lr, betas=betas, eps=eps)


def set_lr(optimizer: torch.optim.Optimizer, lr: float, step: int, warmup: int) -> float:
    """Linear warm-up to `lr` over `warmup` steps, then constant; returns the rate set."""
    rate = lr * min(1.0, (step + 1) / max(warmup, 1))
    for group in optimizer.param_groups:
        group["lr"] = rate
    return rate


class EMA:
    """Exponential moving average of a model's weights (fp32), with the usual early warm-up."""

    def __init__(self, model: nn.Module, decay: float = 0.999):
        self.decay = decay
        self.shadow = {k: v.detach().float().clone() for k, v in model.state_dict().items()}

    def decay_at(self, step: int) -> float:
        # Early on the average would be dominated by the random init: (1+n)/(10+n) ramps it in.
        return min(self.decay, (1 + step) / (10 + step))

    @torch.no_grad()
    def update(self, model: nn.Module, step: int) -> None:
        """shadow ← d·shadow + (1 − d)·weights."""
        d = self.decay_at(step)
        for name, value in model.state_dict().items():
            self.shadow[name].lerp_(value.float(), 1 - d)

    def copy_to(self, model: nn.Module) -> nn.Module:
        """Load the averaged weights into `model` (same architecture); returns it."""
        model.load_state_dict({k: v.to(model.state_dict()[k].dtype) for k, v in self.shadow.items()})
        return model


def save_checkpoint(run: Path, step: int, modules: dict[str, dict[str, torch.Tensor]],
                    optimizer: torch.optim.Optimizer, extra: dict | None = None, keep: int = 2) -> Path:
    """Write a checkpoint of `step` and point latest.json at it; keeps the newest `keep`."""
    root = Path(run) / CHECKPOINT_DIR
    folder = root / f"step_{step:07d}"
    tmp = root / f".tmp_{step:07d}_{os.getpid()}"
    shutil.rmtree(tmp, ignore_errors=True)
    tmp.mkdir(parents=True)
    for name, state in modules.items():
        save_file({k: v.detach().contiguous().cpu() for k, v in state.items()}, tmp / f"{name}.safetensors")
    torch.save(optimizer.state_dict(), tmp / "optimizer.pt")
    (tmp / "state.json").write_text(json.dumps({"step": step, **(extra or {})}, indent=1))
    shutil.rmtree(folder, ignore_errors=True)
    os.replace(tmp, folder)
    latest_tmp = root / f".{LATEST}.{os.getpid()}.tmp"
    latest_tmp.write_text(json.dumps({"step": step, "folder": folder.name}))
    os.replace(latest_tmp, root / LATEST)
    for old in sorted(p for p in root.glob("step_*") if p.is_dir())[:-keep]:
        shutil.rmtree(old, ignore_errors=True)
    return folder


def load_checkpoint(run: Path, module_names: list[str]) -> dict | None:
    """The latest checkpoint of a run as {"step", "modules": {name: state}, "optimizer", "extra"}, or None."""
    root = Path(run) / CHECKPOINT_DIR
    if not (root / LATEST).is_file():
        return None
    folder = root / json.loads((root / LATEST).read_text())["folder"]
    extra = json.loads((folder / "state.json").read_text())
    return {
        "step": int(extra.pop("step")),
        "modules": {name: load_file(str(folder / f"{name}.safetensors")) for name in module_names},
        "optimizer": torch.load(folder / "optimizer.pt", map_location="cpu", weights_only=True),  # any device resumes
        "extra": extra,
    }


class JsonlLog:
    """Append-only JSONL log; on resume, lines past the checkpoint's step are dropped (they get redone)."""

    def __init__(self, path: Path, resume_step: int | None):
        self.path = Path(path)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        if resume_step is None:
            self.path.write_text("")
        elif self.path.is_file():
            kept = [line for line in self.path.read_text().splitlines()
                    if line.strip() and json.loads(line).get("step", 0) <= resume_step]
            self.path.write_text("".join(line + "\n" for line in kept))

    def write(self, **record) -> None:
        """Append one record (floats rounded to 6 significant digits)."""
        record = {k: (float(f"{v:.6g}") if isinstance(v, float) else v) for k, v in record.items()}
        with self.path.open("a") as f:
            f.write(json.dumps(record) + "\n")


class Clock:
    """Wall-clock budget of a run and the checkpoint cadence."""

    def __init__(self, minutes: float | None, checkpoint_minutes: float):
        self.start = self.last_checkpoint = time.monotonic()
        self.limit = None if minutes is None else minutes * 60.0
        self.every = checkpoint_minutes * 60.0

    def elapsed(self) -> float:
        return time.monotonic() - self.start

    def out_of_time(self) -> bool:
        return self.limit is not None and self.elapsed() >= self.limit

    def checkpoint_due(self) -> bool:
        if time.monotonic() - self.last_checkpoint >= self.every:
            self.last_checkpoint = time.monotonic()
            return True
        return False
