"""Training the small causal video tokenizer on every stream the DiT will ever encode.

The tokenizer must encode rendered RGB, albedo and the three lighting encodings (env_ldr, env_log,
env_dir — all in [-1, 1]), as 9-frame clips and as single images. Each step is, at random, a batch of
clips or a larger batch of images; each crop is a random window of one stream of one
sample (the network is convolutional, so crops train it as well as full frames, for less).
"""

from __future__ import annotations

import math
from dataclasses import asdict, dataclass
from pathlib import Path

import torch
from safetensors.torch import save_file

from relight_core.data.dataset import RelightDataset
from relight_core.precision import autocast, resolve_precision
from relight_core.tokenizer import TOKENIZER_PRESETS, CausalVideoAutoencoder, tokenizer_loss
from relight_core.training.loop import (
    LOG_FILE,
    Clock,
    JsonlLog,
    load_checkpoint,
    make_optimizer,
    save_checkpoint,
    set_lr,
    step_generator,
)

# Stream → sampling weight: relit frames are what the tokenizer must decode well.
STREAM_WEIGHTS = {"input": 0.25, "relit": 0.25, "albedo": 0.2, "env_ldr": 0.1, "env_log": 0.1, "env_dir": 0.1}
FINAL_WEIGHTS = "tokenizer.safetensors"


@dataclass(frozen=True)
class TokenizerTrainConfig:
    """A tokenizer training run."""

    data: Path                           # dataset root (train/ and, for validation, test/)
    run: Path                            # run folder: log.jsonl, ckpt/
    preset: str = "small"
    steps: int = 20000                   # stop after this many steps ...
    minutes: float | None = None         # ... or this much wall time, whichever first
    clip_batch: int = 4                  # clips per video step
    image_batch: int = 16                # images per image step
    clip_frames: int = 9
    crop: int = 64
    lr: float = 2e-4
    betas: tuple[float, float] = (0.9, 0.99)
    weight_decay: float = 0.01
    warmup: int = 100
    kl_weight: float = 1e-4
    grad_clip: float = 1.0
    log_every: int = 10
    val_every: int = 250
    checkpoint_minutes: float = 5.0
    seed: int = 0
    precision: str = "auto"              # compute precision (fp32 weights, bf16 autocast where faster)


def crops_from(sample: dict, streams: list[str], crop: int, generator: torch.Generator) -> list[torch.Tensor]:
    """One random crop [3,T,crop,crop] of each named stream of a dataset sample."""
    _, _, h, w = sample["relit"].shape
    out = []
    for name in streams:
        y = int(torch.randint(0, h - crop + 1, (1,), generator=generator))
        x = int(torch.randint(0, w - crop + 1, (1,), generator=generator))
        out.append(sample[name][:, :, y:y + crop, x:x + crop])
    return out


def available_streams(sample: dict) -> list[str]:
    """The streams a sample really has (no zero placeholders)."""
    names = ["relit", "albedo"]
    if bool(sample["has_input"]):
        names.append("input")
    if bool(sample["has_lighting"]):
        names += ["env_ldr", "env_log", "env_dir"]
    return [n for n in STREAM_WEIGHTS if n in names]


def tokenizer_batch(dataset: RelightDataset, size: int, crop: int, generator: torch.Generator,
                    per_sample: int = 2) -> torch.Tensor:
    """[size,3,T,crop,crop]: `per_sample` streams of each of ⌈size/per_sample⌉ random samples."""
    clips = []
    while len(clips) < size:
        sample = dataset[int(torch.randint(0, len(dataset), (1,), generator=generator))]
        names = available_streams(sample)
        weights = torch.tensor([STREAM_WEIGHTS[n] for n in names])
        picks = torch.multinomial(weights, min(per_sample, len(names)), generator=generator)
        clips += crops_from(sample, [names[i] for i in picks.tolist()], min(crop, *sample["relit"].shape[2:]),
                            generator)
    return torch.stack(clips[:size])                                                # (B, 3, T, crop, crop)


@torch.no_grad()
def validation_l1(model: CausalVideoAutoencoder, dataset: RelightDataset, samples: int = 4,
                  dtype: torch.dtype | None = None) -> float:
    """Mean L1 of full-frame reconstructions (posterior mean) of the first samples' streams.

    Computed in `dtype` (default: the `auto` precision of this CPU, precision.py)."""
    dtype = dtype or resolve_precision("auto", "cpu")
    model.eval()
    total, count = 0.0, 0
    for index in range(min(samples, len(dataset))):
        sample = dataset[index]
        video = torch.stack([sample[n] for n in available_streams(sample)])         # (S, 3, T, H, W)
        with autocast(dtype):
            recon = model.decode_raw(model.posterior(video)[0]).float()
        total += (recon.clamp(-1, 1) - video).abs().mean().item()
        count += 1
    model.train()
    return total / max(count, 1)


def train_tokenizer(config: TokenizerTrainConfig, progress: bool = True) -> Path:
    """Train (or resume) a tokenizer run; returns the final weights, <run>/ckpt/tokenizer.safetensors."""
    run = Path(config.run)
    dtype = resolve_precision(config.precision, "cpu")
    videos = RelightDataset(config.data, "train", clip_frames=config.clip_frames, seed=config.seed)
    images = RelightDataset(config.data, "train", clip_frames=1, seed=config.seed + 1)
    test_dir = Path(config.data) / "test"
    val = RelightDataset(config.data, "test", clip_frames=config.clip_frames) if test_dir.is_dir() else None

    model = CausalVideoAutoencoder(TOKENIZER_PRESETS[config.preset])
    optimizer = make_optimizer(model, config.lr, config.betas, config.weight_decay)
    state = load_checkpoint(run, ["model"])
    step = 0
    if state is not None:
        model.load_state_dict(state["modules"]["model"])
        optimizer.load_state_dict(state["optimizer"])
        step = state["step"]
    log = JsonlLog(run / LOG_FILE, step if state is not None else None)
    if state is None:
        log.write(step=0, event="start", config={k: str(v) for k, v in asdict(config).items()},
                  train_samples=len(videos), params=sum(p.numel() for p in model.parameters()))
    clock = Clock(config.minutes, config.checkpoint_minutes)
    model.train()

    def checkpoint() -> None:
        save_checkpoint(run, step, {"model": model.state_dict()}, optimizer)

    while step < config.steps and not clock.out_of_time():
        generator = step_generator(config.seed, step)
        is_image = bool(torch.rand(1, generator=generator) < 0.5)
        dataset = images if is_image else videos
        dataset.set_epoch(step)
        video = tokenizer_batch(dataset, config.image_batch if is_image else config.clip_batch,
                                config.crop, generator)
        lr = set_lr(optimizer, config.lr, step, config.warmup)
        torch.manual_seed(int(torch.randint(0, 2 ** 31 - 1, (1,), generator=generator)))  # posterior sampling
        with autocast(dtype):
            losses = tokenizer_loss(model, video, config.kl_weight)
        optimizer.zero_grad(set_to_none=True)
        losses["loss"].backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(model.parameters(), config.grad_clip)
        if not math.isfinite(float(grad_norm)):
            raise FloatingPointError(f"non-finite gradient at step {step}; lower the learning rate")
        optimizer.step()
        step += 1
        if step % config.log_every == 0:
            record = {k: float(v.detach()) for k, v in losses.items()}
            log.write(step=step, kind="image" if is_image else "video", lr=lr, grad_norm=float(grad_norm),
                      seconds=round(clock.elapsed(), 1), **record)
            if progress:
                print(f"tokenizer step {step}: loss {record['loss']:.4f} l1 {record['l1']:.4f} "
                      f"({clock.elapsed():.0f}s)", flush=True)
        if val is not None and step % config.val_every == 0:
            log.write(step=step, val_l1=validation_l1(model, val, dtype=dtype), seconds=round(clock.elapsed(), 1))
        if clock.checkpoint_due():
            checkpoint()
    checkpoint()
    if val is not None:
        log.write(step=step, val_l1=validation_l1(model, val, dtype=dtype), seconds=round(clock.elapsed(), 1),
                  event="end")
    out = run / "ckpt" / FINAL_WEIGHTS
    save_file({k: v.contiguous() for k, v in model.state_dict().items()}, str(out))
    return out
