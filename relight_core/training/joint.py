"""Training the joint relighting DiT on cached latents, and exporting its EMA as a model folder."""

from __future__ import annotations

import copy
import datetime
import math
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path

import torch
from torch.nn.parallel import DistributedDataParallel

from relight_core.checkpoint import MODEL_PRESETS, ModelSpec, save_model
from relight_core.data.dataset import RelightDataset
from relight_core.diffusion import ConditionedDenoiser, EDMPrecond, edm_loss, sample_training_sigma
from relight_core.dit import JointDiT, network
from relight_core.precision import autocast, resolve_precision
from relight_core.tokenizer import build_tokenizer
from relight_core.training.distributed import Ranks, agree, barrier, global_sum, rank_rows
from relight_core.training.latents import LatentSet, build_latent_set
from relight_core.training.loop import (
    EMA,
    LOG_FILE,
    Clock,
    JsonlLog,
    load_checkpoint,
    make_optimizer,
    save_checkpoint,
    set_lr,
    step_generator,
)
from relight_core.training.recipe import MODES, SIGMA_MAX, Example, Recipe, denoising_loss, make_example


@dataclass(frozen=True)
class DiTTrainConfig:
    """A DiT training run on top of a frozen, trained tokenizer."""

    data: Path                           # dataset root (train/ and, for validation, test/)
    run: Path                            # run folder: log.jsonl, ckpt/
    tokenizer: Path                      # tokenizer weights written by train-tokenizer
    tokenizer_preset: str = "small"
    preset: str = "small"                # MODEL_PRESETS entry the DiT config and defaults come from
    steps: int = 100000                  # stop after this many steps ...
    minutes: float | None = None         # ... or this much wall time, whichever first
    video_batch: int = 4                 # clips per video step
    image_batch: int = 8                 # images per image step (1-frame clips: half the tokens)
    image_fraction: float = 0.5          # share of image steps (paper stage 1: 1:1)
    lr: float = 2e-4                     # from scratch; the paper's 2e-5 is for fine-tuning 7B
    betas: tuple[float, float] = (0.9, 0.99)
    weight_decay: float = 0.01           # the paper's 0.1 is for a pre-trained 7B; small model: less
    warmup: int = 200
    grad_clip: float = 1.0
    ema_decay: float = 0.999
    log_every: int = 10
    val_every: int = 250
    checkpoint_minutes: float = 5.0
    seed: int = 0
    cache: Path = Path("cache/latents")
    export: Path | None = None           # write the EMA model folder here at the end
    recipe: Recipe = field(default_factory=Recipe)
    precision: str = "auto"              # compute precision (fp32 weights, bf16 autocast where faster)


def draw_batch(latents: LatentSet, config: DiTTrainConfig, generator: torch.Generator) -> tuple[dict, bool]:
    """A random video or image batch of latents (image with probability `image_fraction`)."""
    is_image = bool(torch.rand(1, generator=generator) < config.image_fraction)
    size = config.image_batch if is_image else config.video_batch
    indices = torch.randint(0, len(latents), (size,), generator=generator).tolist()
    frames = torch.randint(0, latents.num_image_frames, (size,), generator=generator).tolist() if is_image else None
    return latents.batch(indices, frames), is_image


def train_step(dit: JointDiT, batch: dict, recipe: Recipe, generator: torch.Generator,
               dtype: torch.dtype | None = None) -> tuple[torch.Tensor, dict]:
    """Loss of one batch computed in `dtype` (default: this CPU's `auto` precision, precision.py; bf16
    and fp16 as autocast over fp32 weights), backward not taken; also the drawn modes."""
    dtype = dtype or resolve_precision("auto", "cpu")
    example = make_example(batch["input"], batch["relit"], batch["albedo"], batch["lighting"], recipe, generator,
                           batch["has_input"], batch["has_lighting"])
    with autocast(dtype, batch["relit"].device):
        loss, sigma = denoising_loss(dit, example, recipe, generator)
    return loss, mode_counts(example)


def mode_counts(example: Example) -> dict:
    """How many samples of a batch train each conditioning mode, and how many without lighting."""
    counts = {f"n_{m}": int((example.modes == i).sum()) for i, m in enumerate(MODES)}
    counts["n_no_light"] = int(example.lighting_dropped.sum())
    return counts


def train_step_rows(dit, batch: dict, recipe: Recipe, generator: torch.Generator, rows: slice,
                    dtype: torch.dtype) -> tuple[torch.Tensor, dict]:
    """`train_step` of a global batch with the network run on `rows` only (one rank's share, DDP).

    Every random draw is made for the whole batch, in `denoising_loss`'s order, and then sliced, so
    a row gets the same modes, σ and noise whichever rank computes it. Returns the rows' mean loss
    times their share of the batch (the shares of all ranks sum to `train_step`'s loss; with every
    row, it is that loss exactly) and the whole batch's mode counts.
    """
    example = make_example(batch["input"], batch["relit"], batch["albedo"], batch["lighting"], recipe, generator,
                           batch["has_input"], batch["has_lighting"])
    x0, mask = example.x0, example.condition_mask                             # (B, 16, 3t, h, w), (B, 1, 3t, 1, 1)
    b, device = x0.shape[0], generator.device
    sigma = sample_training_sigma(b, recipe.p_mean, recipe.p_std, generator)                      # (B,)
    if recipe.p_sigma_max > 0:
        at_max = torch.rand(b, generator=generator, device=device) < recipe.p_sigma_max
        sigma = torch.where(at_max, torch.full_like(sigma, SIGMA_MAX), sigma)
    sigma = sigma.to(x0.device)
    noise = torch.randn(x0.shape, generator=generator, device=device).to(x0.device)   # (B, 16, 3t, h, w)
    seed = int(torch.randint(0, 2 ** 31 - 1, (1,), generator=generator, device=device))
    denoiser = ConditionedDenoiser(EDMPrecond(partial(network, dit)), x0, mask,
                                   augment_sigma=recipe.augment_sigma, seed=seed, residual=recipe.residual)
    # The condition-clip noise was drawn for the whole batch too: keep this rank's rows of it.
    denoiser.condition_latent, denoiser.condition_mask = x0[rows], mask[rows]
    denoiser.augmented = denoiser.augmented[rows]
    with autocast(dtype, x0.device):
        denoised = denoiser(x0[rows] + sigma[rows].view(-1, 1, 1, 1, 1) * noise[rows], sigma[rows],
                            lighting=example.lighting[rows])                 # (b, 16, 3t, h, w)
        loss = edm_loss(denoised, x0[rows], sigma[rows], recipe.clip_weights, condition_mask=mask[rows])
    return loss * ((rows.stop - rows.start) / b), mode_counts(example)


@torch.no_grad()
def validation_loss(dit: JointDiT, latents: LatentSet, recipe: Recipe, seed: int, batch: int = 4,
                    max_items: int = 32, dtype: torch.dtype | None = None,
                    device: torch.device | str = "cpu") -> float:
    """Mean loss over the first items' full clips in the default mode with lighting, fixed noise
    (computed on `device`, where `dit` is)."""
    recipe = replace(recipe, p_albedo_only=0.0, p_both=0.0, p_drop_lighting=0.0, p_continue=0.0)
    generator = step_generator(seed, 0, stream=1)
    was_training = dit.training
    dit.eval()
    items = list(range(min(max_items, len(latents))))
    total = 0.0
    for start in range(0, len(items), batch):
        chunk = items[start:start + batch]
        loss, _ = train_step(dit, to_device(latents.batch(chunk), device), recipe, generator, dtype)
        total += float(loss) * len(chunk)
    dit.train(was_training)
    return total / max(len(items), 1)


def to_device(batch: dict, device: torch.device | str) -> dict:
    """A batch of latents on `device` (the same tensors when they are there already)."""
    return {k: v.to(device) for k, v in batch.items()}


def export_model(out: Path, preset: str, dit: JointDiT, tokenizer, tokenizer_preset: str, size: int,
                 clip_frames: int, notes: dict, dtype: torch.dtype = torch.bfloat16) -> Path:
    """Write a model folder: the preset's spec marked trained, at the training size and clip length.

    The DiT is stored in `dtype` (bf16 halves the shipped file; loading casts it to whatever precision
    the machine computes in, see precision.py); the tokenizer stays fp32 (it is small). `chunk_frames`
    is the training clip length with a one-frame overlap, the continuation the recipe trains.
    """
    spec: ModelSpec = replace(MODEL_PRESETS[preset], name=f"{preset}-trained",
                              tokenizer={"type": "causal-ae", "preset": tokenizer_preset},
                              size=size, chunk_frames=clip_frames, overlap_frames=1 if clip_frames > 1 else 0,
                              trained=True, notes=notes)
    return save_model(out, spec, copy.deepcopy(dit).to(dtype), tokenizer)


def shared_latents(dataset: RelightDataset, tokenizer, config: DiTTrainConfig, progress: bool,
                   dtype: torch.dtype, ranks: Ranks) -> LatentSet:
    """A split's latents on every rank; under DDP each rank first encodes its shard into the cache."""
    if ranks.group:
        build_latent_set(dataset, tokenizer, config.cache, progress, dtype, shard=(ranks.rank, ranks.world))
        barrier(ranks)
    return build_latent_set(dataset, tokenizer, config.cache, progress, dtype)


def train_dit(config: DiTTrainConfig, progress: bool = True, command: str | None = None,
              ranks: Ranks | None = None) -> dict:
    """Train (or resume) a DiT run; exports the EMA model when `config.export` is set. Returns a summary.

    `ranks` places the run: one process on the CPU by default, one rank of a data-parallel run
    under torchrun (`distributed.join`), where rank 0 alone writes the log, checkpoints and export.
    """
    ranks = ranks or Ranks()
    progress = progress and ranks.main
    run = Path(config.run)
    device = ranks.device
    dtype = resolve_precision(config.precision, device)
    latent_dtype = resolve_precision(config.precision, "cpu")   # latents are encoded on the CPU
    tokenizer = build_tokenizer({"type": "causal-ae", "preset": config.tokenizer_preset,
                                 "weights": str(Path(config.tokenizer).resolve())})
    tokenizer.requires_grad_(False)
    train_data = RelightDataset(config.data, "train")
    latents = shared_latents(train_data, tokenizer, config, progress, latent_dtype, ranks)
    has_test = (Path(config.data) / "test").is_dir()
    val_latents = shared_latents(RelightDataset(config.data, "test"), tokenizer, config, progress, latent_dtype,
                                 ranks) if has_test else None

    spec = MODEL_PRESETS[config.preset]
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(config.seed)
        dit = JointDiT(spec.dit)
    dit.to(device)
    ema = EMA(dit, config.ema_decay)
    ema_model = copy.deepcopy(dit).requires_grad_(False)
    optimizer = make_optimizer(dit, config.lr, config.betas, config.weight_decay)
    state = load_checkpoint(run, ["dit", "ema"])
    step = 0
    if state is not None:
        dit.load_state_dict(state["modules"]["dit"])
        ema.shadow = {k: v.float().to(device) for k, v in state["modules"]["ema"].items()}
        optimizer.load_state_dict(state["optimizer"])
        step = state["step"]
    log = JsonlLog(run / LOG_FILE, step if state is not None else None) if ranks.main else None
    if log is not None and state is None:
        processes = {"processes": ranks.world} if ranks.group else {}
        log.write(step=0, event="start", config={k: str(v) for k, v in asdict(config).items()},
                  train_items=len(latents), val_items=len(val_latents) if val_latents else 0,
                  params=sum(p.numel() for p in dit.parameters()), **processes)
    clock = Clock(config.minutes, config.checkpoint_minutes)
    dit.train()
    # DDP averages the ranks' gradients while backward runs; its forward is the DiT's.
    net = DistributedDataParallel(dit, device_ids=[device.index] if device.type == "cuda" else None) \
        if ranks.group else dit
    last = {}

    def checkpoint() -> None:
        save_checkpoint(run, step, {"dit": dit.state_dict(), "ema": ema.shadow}, optimizer)

    def validate(**extra) -> float:
        value = validation_loss(ema.copy_to(ema_model), val_latents, config.recipe, config.seed, dtype=dtype,
                                device=device)
        log.write(step=step, val_loss=value, seconds=round(clock.elapsed(), 1), **extra)
        last["val_loss"] = value
        return value

    while step < config.steps and not agree(clock.out_of_time(), ranks):
        generator = step_generator(config.seed, step)
        batch, is_image = draw_batch(latents, config, generator)
        batch = to_device(batch, device)
        lr = set_lr(optimizer, config.lr, step, config.warmup)
        if ranks.group:
            rows = rank_rows(len(batch["relit"]), ranks.rank, ranks.world)
            share, counts = train_step_rows(net, batch, config.recipe, generator, rows, dtype)
            objective = share * ranks.world                      # DDP averages: the sum of the shares
        else:
            share, counts = train_step(dit, batch, config.recipe, generator, dtype)
            objective = share
        optimizer.zero_grad(set_to_none=True)
        objective.backward()
        grad_norm = torch.nn.utils.clip_grad_norm_(dit.parameters(), config.grad_clip)
        if not math.isfinite(float(grad_norm)):
            raise FloatingPointError(f"non-finite gradient at step {step}; lower the learning rate")
        optimizer.step()
        ema.update(dit, step)
        step += 1
        last["loss"] = float(global_sum(share.detach(), ranks))                  # the global batch's loss
        if log is not None and step % config.log_every == 0:
            log.write(step=step, loss=last["loss"], kind="image" if is_image else "video", lr=lr,
                      grad_norm=float(grad_norm), seconds=round(clock.elapsed(), 1), **counts)
            if progress:
                print(f"dit step {step}: loss {last['loss']:.4f} ({clock.elapsed():.0f}s)", flush=True)
        if log is not None and val_latents is not None and step % config.val_every == 0:
            validate()
        if ranks.main and clock.checkpoint_due():
            checkpoint()
    if ranks.main:
        checkpoint()
        if val_latents is not None:
            validate(event="end")
    summary = {"steps": step, "train_items": len(latents), "val_items": len(val_latents) if val_latents else 0,
               "seconds_this_session": round(clock.elapsed(), 1), **last}
    if ranks.main and config.export is not None:
        clip = latents.scenes[0]["albedo/video"]                                      # (16, t, h, w)
        size = max(clip.shape[-2:]) * tokenizer.spatial_factor
        frames = 1 + (clip.shape[1] - 1) * tokenizer.temporal_factor
        notes = {**summary, "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC"),
                 "data": str(config.data), "tokenizer": str(config.tokenizer), "command": command,
                 "recipe": asdict(config.recipe)}
        export_model(Path(config.export), config.preset, ema.copy_to(ema_model).cpu(), tokenizer,
                     config.tokenizer_preset, size, frames, notes)
        summary["export"] = str(config.export)
    return summary
