"""Train the default model — a pixel-tokenizer joint DiT — on an image pack, on a GPU or the CPU.

The default model's tokenizer is the lossless `PixelTokenizer` (8×8 RGB patches, 192 channels),
so there is nothing to encode ahead of time: batches are cut from a pack (`training.pack`) held in
(GPU) memory, flipped at random, and turned into latents on the fly. The recipe is the project's
UniRelight recipe (`training.recipe`: conditioning mix, lighting dropout, EDM loss, condition clips
fed as at inference), with every random draw on the training device.

    python -m relight_core.training.fast --pack cache/train.npz --test-pack cache/test.npz \
        --minutes 7 --device cuda --out runs/default-pixel

Writes `<out>/model/` (config.json + dit.safetensors, the EMA in bf16; also as ≤15 MB shards
`<out>/dit-shard-*.safetensors` + `<out>/config.json` that `merge_shards` joins, rewritten every
`--export-every-minutes`), `<out>/log.jsonl` and, at the end, sampled
PSNR on train and test items (`<out>/samples.json`). `--init DIR` starts from a model folder's
DiT (to continue from the shipped weights; `--zero-head` zeroes its output layer). `--residual`
trains relit/albedo as offsets from the input (`ModelSpec.residual`), `--p-sigma-max` trains a
share of samples at σ = 80 (the one-step sampler's call), `--mix-lights` relights a share of items
between mixtures of their scene's two probes (`make_batch`), `--crop` cuts a share of items as zoomed
crops of the packs' full-size images (`crop_items`). `--val-pack` (scenes kept out of training) scores
the EMA's sampled relit + albedo PSNR on them at step 0, every `--val-every-minutes` and at the end,
and the best of those EMAs is the one exported (the weights `--init` gave when nothing beats them):
a long run on few scenes cannot end overfitted. `<out>/checkpoint.pt` (every
`--checkpoint-every-minutes` and at the end) makes a run started again on the same `--out` resume
exactly where it stopped. `--pack` takes several packs (e.g. scenes of different dataset seeds),
trained as one (`pack.load_packs`).
"""

from __future__ import annotations

import argparse
import copy
import datetime
import json
import math
import time
from dataclasses import asdict, dataclass, field, replace
from functools import partial
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from relight_core import lighting
from relight_core.checkpoint import CONFIG_FILE, DIT_FILE, ModelSpec
from relight_core.colour import linear_to_srgb, permute_colours, srgb_to_linear
from relight_core.diffusion import ConditionedDenoiser, EDMPrecond, sample_res2ab, sampling_sigmas
from relight_core.dit import DiTConfig, JointDiT, pack_lighting
from relight_core.devices import resolve_device
from relight_core.errors import InputError
from relight_core.precision import resolve_precision
from relight_core.tokenizer import PixelTokenizer
from relight_core.training.loop import EMA, make_optimizer
from relight_core.training.pack import PackMismatch, load_pack, load_packs
from relight_core.training.recipe import Recipe, denoising_loss, make_example, network

SHARD_BYTES = 15_000_000


@dataclass(frozen=True)
class FastConfig:
    pack: Path | tuple[Path, ...]         # one pack, or several trained as one (load_packs)
    out: Path
    test_pack: Path | None = None
    minutes: float = 7.0
    device: str = "auto"                 # cuda when available, else cpu
    batch: int = 128
    accumulate: int = 1                  # micro-batches of `batch` items per optimizer step (a CPU's big batch)
    lr: float = 4e-4
    min_lr_fraction: float = 0.1         # cosine decay over the time budget down to this fraction
    warmup: int = 200
    weight_decay: float = 0.01
    grad_clip: float = 1.0
    ema_decay: float = 0.999
    width: int = 384
    depth: int = 8
    num_heads: int = 6
    patch: int = 8
    seed: int = 0
    log_every: int = 50
    eval_items: int = 32
    eval_steps: int = 20
    init: Path | None = None
    model_dir: Path | None = None        # the model folder (default <out>/model)
    export_every_minutes: float = 2.0    # shards + config.json of the EMA so far, in <out>
    compile: bool = False                # torch.compile the DiT for training (falls back to eager)
    zero_head: bool = False              # zero the output layer after --init (a new parameterisation)
    export_steps: int = 1                # the exported model's default sampling steps
    checkpoint_every_minutes: float = 5.0  # <out>/checkpoint.pt (weights, EMA, optimizer, RNG): exact resume
    train_size: int | None = None        # shrink the packs' images to this side (px) first; the model's size
    mix_lights: float = 0.0              # share of items relit between mixtures of their two probes (make_batch)
    crop: float = 0.0                    # share of items cut as a zoomed crop of the full-size pack (crop_items)
    crop_min: float = 0.5                # the smallest crop's side, a fraction of the frame's
    permute_colours: bool = False        # each item's RGB channels in one of the six orders, probe alike (make_batch)
    val_pack: Path | None = None         # held-out scenes: the EMA is scored on them and the best one exported
    val_every_minutes: float = 1.0       # how often (and at step 0 and the end)
    val_items: int = 128
    recipe: Recipe = field(default_factory=Recipe)


def dit_config(config: FastConfig) -> DiTConfig:
    return DiTConfig(width=config.width, depth=config.depth, num_heads=config.num_heads,
                     adaln_lora_dim=64, patch_spatial=1, out_channels=3 * config.patch ** 2)


def _video(x: torch.Tensor) -> torch.Tensor:
    """[B,3,H,W] → [B,3,1,H,W]."""
    return x[:, :, None]


def shrink_pack(pack: dict, size: int, multiple: int = 8) -> dict:
    """The pack with its images' long side shrunk to `size` px (sides multiples of `multiple`, the
    tokenizer's patch), as the CLI and studio shrink frames for the model (`media.target_size`,
    antialiased bilinear); the probes stay (they are re-gridded to the frames' size per batch)."""
    from relight_core.media import target_size

    height, width = pack["rgb"].shape[-2:]
    if size > max(height, width) or size % multiple:
        raise ValueError(f"--train-size {size} must be a multiple of {multiple} no larger than the pack's "
                         f"{max(height, width)} px")
    H, W = target_size(height, width, size, multiple)
    if (H, W) == (height, width):
        return pack
    out = dict(pack)
    out["rgb"] = _to_uint8(_shrink(pack["rgb"], (H, W)))
    out["albedo"] = _to_uint8(_shrink(pack["albedo"], (H, W)))
    out["mask"] = _shrink(pack["mask"], (H, W)) > 0.5
    return out


def _shrink(images: torch.Tensor, size: tuple[int, int]) -> torch.Tensor:
    """Images [..., h, w] (uint8 or bool) shrunk to `size` as float: antialiased bilinear, each plane alone."""
    lead, (height, width) = images.shape[:-2], images.shape[-2:]
    x = images.reshape(-1, 1, height, width).float()
    x = torch.nn.functional.interpolate(x, size=size, mode="bilinear", antialias=True, align_corners=False)
    return x.reshape(*lead, *size)


def _to_uint8(images: torch.Tensor) -> torch.Tensor:
    return images.round().clamp(0, 255).to(torch.uint8)


def crop_draws(batch: int, share: float, smallest: float, generator: torch.Generator,
               device: torch.device) -> torch.Tensor:
    """`crop_items`' crops [B,3]: (side as a fraction of the frame's, from U(smallest, 1); left and top
    as fractions of the room left), side 1 for the items not cropped (1 − `share` of them)."""
    draw = torch.rand(batch, 4, generator=generator, device=device)
    side = torch.where(draw[:, 0] < share, smallest + (1 - smallest) * draw[:, 1], torch.ones_like(draw[:, 1]))
    return torch.stack([side, draw[:, 2], draw[:, 3]], dim=1)


def crop_items(full: dict, small: dict, indices: torch.Tensor, crops: torch.Tensor) -> dict:
    """The batch's items as a pack of their own (rgb, albedo, env; index it with arange): an item whose
    crop side is 1 is the `small` (shrunk) pack's; the others are a crop of the `full`-size pack's images
    shrunk to the small size (antialiased bilinear, as `shrink_pack`); a crop is never smaller than the
    small size (never enlarged). Exact for the task: a crop of the sensor is the same camera looking the
    same way, so the camera-frame probes stay as they are; the model sees its scenes at up to 1/side × the
    detail of the training size."""
    rgb, albedo = small["rgb"][indices].clone(), small["albedo"][indices].clone()
    height, width = full["rgb"].shape[-2:]
    size = rgb.shape[-2:]
    for i in torch.nonzero(crops[:, 0] < 1).flatten().tolist():
        side, left, top = crops[i].tolist()
        h, w = max(size[0], round(side * height)), max(size[1], round(side * width))
        y, x = round(top * (height - h)), round(left * (width - w))
        item = int(indices[i])
        rgb[i] = _to_uint8(_shrink(full["rgb"][item][..., y:y + h, x:x + w], tuple(size)))
        albedo[i] = _to_uint8(_shrink(full["albedo"][item][..., y:y + h, x:x + w], tuple(size)))
    return {"rgb": rgb, "albedo": albedo, "env": small["env"][indices]}


def make_batch(pack: dict, tokenizer: PixelTokenizer, indices: torch.Tensor, target: torch.Tensor,
               flip: torch.Tensor, mix: torch.Tensor | None = None,
               colours: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Latents of items: input (the other light), relit (light `target`), albedo, lighting [B,579,1,h,w].

    `flip` mirrors image and probe left↔right (u → 1−u in the camera panorama: the mirrored scene
    under the mirrored light), env_dir staying what it is for every pixel.

    `colours` [B,3] (optional, a permutation of 0–2 per item) reorders each item's RGB channels in its frames
    and its probe alike (`colour.permute_colours`: the data engine renders each channel on its own, the principled
    BSDF's tints being off, so that is the scene with its colours and its light's reordered).

    `mix` [B,2] (optional) relights with mixtures of the scene's two probes: light transport is linear
    in the light, so the scene under w·probe[t] + (1−w)·probe[1−t] is w·image[t] + (1−w)·image[1−t]
    in linear light (the two renders share their sampler seed). Column 0 is the target's weight w on
    light `target`, column 1 the input's weight on it; (1, 0) is the unmixed item. The images are
    mixed after undoing the sRGB curve and encoded again; the probes on the lighting grid are linear.
    """
    arange = torch.arange(len(indices), device=indices.device)
    rgb = pack["rgb"][indices]                                                  # (B, 2, 3, H, W) uint8
    env = pack["env"][indices, target]                                           # (B, s, s, 3)
    if mix is None:
        relit = rgb[arange, target].float() / 127.5 - 1
        source = rgb[arange, 1 - target].float() / 127.5 - 1
    else:
        linear = srgb_to_linear(rgb.float() / 255)
        on, off = linear[arange, target], linear[arange, 1 - target]
        w = mix.to(linear.dtype).view(-1, 2, 1, 1, 1)
        relit = linear_to_srgb(w[:, 0] * on + (1 - w[:, 0]) * off) * 2 - 1
        source = linear_to_srgb(w[:, 1] * on + (1 - w[:, 1]) * off) * 2 - 1
        w_env = mix[:, 0].to(env.dtype).view(-1, 1, 1, 1)
        env = w_env * env + (1 - w_env) * pack["env"][indices, 1 - target]
    albedo = pack["albedo"][indices].float() / 127.5 - 1
    f = flip.view(-1, 1, 1, 1)
    relit, source, albedo = (torch.where(f, x.flip(-1), x) for x in (relit, source, albedo))
    env = torch.where(f, env.flip(2), env)
    if colours is not None:
        relit, source, albedo = (permute_colours(x, colours) for x in (relit, source, albedo))
        env = permute_colours(env, colours, dim=-1)
    height, width = relit.shape[-2:]
    encoded = lighting.encode_lighting(lighting.upsample_panorama(env, height, width))
    light = [tokenizer.encode(_video(encoded[k].to(relit.device).permute(0, 3, 1, 2)))
             for k in ("env_ldr", "env_log", "env_dir")]
    return {"input": tokenizer.encode(_video(source)), "relit": tokenizer.encode(_video(relit)),
            "albedo": tokenizer.encode(_video(albedo)), "lighting": pack_lighting(*light)}


def light_mix(batch: int, share: float, generator: torch.Generator, device: torch.device) -> torch.Tensor:
    """`make_batch`'s mix [B,2]: a `share` of items get the target's weight on its light drawn from
    U(0.5, 1) and the input's from U(0, 0.5) — each still mostly one probe, so every item remains a
    relighting from one light towards the other, under the continuum of lights between the two;
    the rest stay unmixed (1, 0), the task the model is used for."""
    draw = torch.rand(batch, 3, generator=generator, device=device)
    mixed = draw[:, :1] < share
    weights = torch.stack([0.5 + 0.5 * draw[:, 1], 0.5 * draw[:, 2]], dim=1)
    return torch.where(mixed, weights, torch.tensor([1.0, 0.0], device=device))


@torch.no_grad()
def sample_relight(dit: JointDiT, batch: dict, steps: int, seed: int = 0, autocast: bool = True,
                   residual: bool = False, final_denoise: bool = True) -> torch.Tensor:
    """Default-mode sampling (input → relit + albedo) as `Relighter` runs it (no residual gain; the
    schedule of `diffusion.sampling_sigmas(steps, final_denoise)`); x0 [B,C,3,h,w]."""
    inp = batch["input"]
    b, _, t = inp.shape[:3]
    condition = torch.cat([inp, torch.zeros_like(inp), torch.zeros_like(inp)], dim=2)
    mask = torch.zeros(b, 1, 3 * t, 1, 1, device=inp.device)
    mask[:, :, :t] = 1.0
    denoiser = ConditionedDenoiser(EDMPrecond(partial(network, dit)), condition, mask, seed=seed, residual=residual)
    generator = torch.Generator(device=inp.device).manual_seed(seed)
    noise = torch.randn(condition.shape, generator=generator, device=inp.device)
    sigmas = sampling_sigmas(steps, final_denoise).to(inp.device)
    with torch.autocast(inp.device.type, dtype=torch.bfloat16, enabled=autocast):
        return sample_res2ab(lambda x, s, **kw: denoiser(x, s, lighting=batch["lighting"]),
                             noise * sigmas[0], sigmas).float()


def psnr(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Per-item PSNR of [-1,1] images [B,...] (peak 2)."""
    mse = ((a - b) ** 2).flatten(1).mean(1).clamp_min(1e-10)
    return 10 * torch.log10(4 / mse)


@torch.no_grad()
def sampled_quality(dit: JointDiT, pack: dict, tokenizer: PixelTokenizer, items: int, steps: int,
                    autocast: bool, residual: bool = False) -> dict[str, float]:
    """Mean PSNR of sampled relit/albedo on the first items (light 1 → 0), the input-copy floor and the
    probe-following margin (PSNR to the target minus PSNR to the same scene under the other probe)."""
    n = min(items, len(pack["rgb"]))
    device = pack["rgb"].device
    idx = torch.arange(n, device=device)
    out = {"relit": [], "albedo": [], "floor": [], "margin": []}
    for start in range(0, n, 16):
        sub = idx[start:start + 16]
        target = torch.zeros_like(sub)
        batch = make_batch(pack, tokenizer, sub, target, torch.zeros_like(sub, dtype=torch.bool))
        x0 = sample_relight(dit, batch, steps, autocast=autocast, residual=residual)
        t = batch["input"].shape[2]
        relit = tokenizer.decode(x0[:, :, t:2 * t])
        albedo = tokenizer.decode(x0[:, :, 2 * t:])
        target_img, input_img = tokenizer.decode(batch["relit"]), tokenizer.decode(batch["input"])
        out["relit"].append(psnr(relit, target_img))
        out["albedo"].append(psnr(albedo, tokenizer.decode(batch["albedo"])))
        out["floor"].append(psnr(input_img, target_img))
        out["margin"].append(psnr(relit, target_img) - psnr(relit, input_img))
    return {k: round(float(torch.cat(v).mean()), 3) for k, v in out.items()}


def selection_score(scores: dict[str, float]) -> float:
    """What "better" means when choosing among models on held-out scenes (`--val-pack`, `training.pick`):
    sampled relit + albedo PSNR (`sampled_quality`'s scores)."""
    return scores["relit"] + scores["albedo"]


def export(out: Path, dit: JointDiT, config: FastConfig, size: int, lighting_size: int, notes: dict,
           model_dir: Path | None = None) -> Path:
    """Transport shards + config.json in `out`; with `model_dir`, also the model folder there
    (EMA DiT in bf16, pixel tokenizer spec)."""
    spec = ModelSpec(name="default-pixel", dit=dit_config(config), tokenizer={"type": "pixel", "patch": config.patch},
                     chunk_frames=1, overlap_frames=0, size=size, steps=config.export_steps, sampler="res2ab",
                     trained=True, lighting_size=lighting_size, residual=config.recipe.residual, notes=notes)
    state = {k: v.detach().to(torch.bfloat16).cpu().contiguous() for k, v in dit.state_dict().items()}
    config_text = json.dumps(spec.to_json(), indent=2)
    (Path(out) / CONFIG_FILE).write_text(config_text)
    if model_dir is not None:
        Path(model_dir).mkdir(parents=True, exist_ok=True)
        save_file(state, Path(model_dir) / DIT_FILE)
        (Path(model_dir) / CONFIG_FILE).write_text(config_text)
    write_shards(state, out)
    return Path(model_dir or out)


def write_shards(state: dict[str, torch.Tensor], out: Path) -> int:
    """A state dict as `dit-shard-<i>.safetensors` files of ≤ SHARD_BYTES each in `out` (what a device
    hands back is ≤ 16 MiB a file); `merge_shards` joins them, so shards an earlier, larger state left
    there go first. Returns the shard count."""
    for old in Path(out).glob("dit-shard-*.safetensors"):
        old.unlink()
    shards: list[dict] = [{}]
    used = 0
    for name, value in state.items():
        nbytes = value.numel() * value.element_size()
        if shards[-1] and used + nbytes > SHARD_BYTES:
            shards.append({})
            used = 0
        shards[-1][name] = value.contiguous()
        used += nbytes
    for i, shard in enumerate(shards):
        save_file(shard, Path(out) / f"dit-shard-{i}.safetensors")
    return len(shards)


def merge_shards(shard_dir: Path, config_json: Path, folder: Path) -> Path:
    """Join `dit-shard-*.safetensors` + a config.json into a model folder."""
    state = {}
    for path in sorted(Path(shard_dir).glob("dit-shard-*.safetensors")):
        state.update(load_file(str(path)))
    folder.mkdir(parents=True, exist_ok=True)
    save_file(state, folder / DIT_FILE)
    (folder / CONFIG_FILE).write_text(Path(config_json).read_text())
    return folder


def train(config: FastConfig) -> dict:
    device = resolve_device(None if config.device == "auto" else config.device)
    started = time.time()
    torch.manual_seed(config.seed)
    if device.type == "cuda":
        torch.backends.cuda.matmul.allow_tf32 = True
        torch.backends.cudnn.allow_tf32 = True
    pack = load_packs(config.pack, device)
    full = pack  # crops (--crop) are cut from the images at the pack's size
    test = load_pack(config.test_pack, device) if config.test_pack else None
    val = load_pack(config.val_pack, device) if config.val_pack else None
    if config.train_size is not None:
        pack = shrink_pack(pack, config.train_size, config.patch)
        test = shrink_pack(test, config.train_size, config.patch) if test is not None else None
        val = shrink_pack(val, config.train_size, config.patch) if val is not None else None
    tokenizer = PixelTokenizer(config.patch)
    size = int(pack["rgb"].shape[-1])
    lighting_size = int(pack["lighting_size"])
    dit = JointDiT(dit_config(config)).to(device)
    if config.init is not None:
        dit.load_state_dict({k: v.float() for k, v in load_file(str(Path(config.init) / DIT_FILE)).items()})
        if config.zero_head:  # the output means something new: start from "predict zero" (copy the input)
            torch.nn.init.zeros_(dit.final_layer.linear.weight)
    ema = EMA(dit, config.ema_decay)
    ema_model = copy.deepcopy(dit).requires_grad_(False)
    optimizer = make_optimizer(dit, config.lr, (0.9, 0.99), config.weight_decay)
    generator = torch.Generator(device=device).manual_seed(config.seed)
    # bf16 autocast where this device runs it faster (GPUs with bf16, AMX or AVX512-BF16 CPUs); fp32 on AVX2 (~80× slower)
    autocast = resolve_precision("auto", device) == torch.bfloat16
    net = torch.compile(dit) if config.compile else dit
    out = Path(config.out)
    out.mkdir(parents=True, exist_ok=True)
    log = (out / "log.jsonl").open("a")
    checkpoint_path = out / "checkpoint.pt"
    resumed = None
    best: dict = {}  # --val-pack: the best EMA so far (state, step, scores)
    if checkpoint_path.exists():  # exact resume: weights, EMA, optimizer, RNG, step and time used
        resumed = torch.load(checkpoint_path, map_location=device, weights_only=True)
        dit.load_state_dict(resumed["dit"])
        ema.shadow = {k: v.to(device) for k, v in resumed["ema"].items()}
        optimizer.load_state_dict(resumed["optimizer"])
        generator.set_state(resumed["generator"].cpu())
        best = resumed.get("best", {})

    def write(**record):
        log.write(json.dumps(record) + "\n")
        log.flush()
        print(json.dumps(record), flush=True)

    params = sum(p.numel() for p in dit.parameters())
    write(event="start", items=len(pack["rgb"]), test_items=len(test["rgb"]) if test else 0, params=params,
          config={k: " ".join(map(str, v)) if k == "pack" and isinstance(v, tuple) else str(v)
                  for k, v in asdict(config).items()}, load_s=round(time.time() - started, 1),
          device=str(torch.cuda.get_device_name(device) if device.type == "cuda" else "cpu"))
    budget = config.minutes * 60
    train_started = time.time()
    step, losses = 0, []
    if resumed is not None:
        train_started -= float(resumed["elapsed"])
        step = int(resumed["step"])
        write(event="resume", step=step, elapsed=round(float(resumed["elapsed"]), 1))
    last_checkpoint = time.time()

    def save_checkpoint():
        partial_path = checkpoint_path.with_suffix(".partial")
        torch.save({"dit": dit.state_dict(), "ema": ema.shadow, "optimizer": optimizer.state_dict(),
                    "generator": generator.get_state(), "step": step,
                    "elapsed": time.time() - train_started, "best": best}, partial_path)
        partial_path.replace(checkpoint_path)  # atomic: a kill mid-write keeps the previous one

    def validate():
        """Score the EMA on the validation pack; keep it when it beats the best so far."""
        nonlocal best, validated
        validated = step
        ema.copy_to(ema_model).eval()
        scores = sampled_quality(ema_model, val, tokenizer, config.val_items, config.eval_steps, autocast,
                                 config.recipe.residual)
        score = selection_score(scores)
        write(event="val", step=step, **scores, best=not best or score > best["score"],
              seconds=round(time.time() - train_started, 1))
        if not best or score > best["score"]:
            best = {"score": score, "step": step, "scores": scores,
                    "state": {k: v.detach().clone() for k, v in ema_model.state_dict().items()}}

    n = len(pack["rgb"])
    last_export = time.time()
    last_val, validated = time.time(), None
    if val is not None and not best:
        validate()
    notes = {"recipe": asdict(config.recipe), "batch": config.batch * config.accumulate, "lr": config.lr}
    if config.mix_lights > 0:
        notes["mix_lights"] = config.mix_lights
    if config.crop > 0:
        notes["crop"] = {"share": config.crop, "smallest": config.crop_min}
    if config.permute_colours:
        notes["permute_colours"] = True
    def micro_step() -> torch.Tensor:
        """Draw `batch` items, backpropagate their loss / accumulate; returns the loss (detached)."""
        indices = torch.randint(0, n, (config.batch,), generator=generator, device=device)
        target = torch.randint(0, 2, (config.batch,), generator=generator, device=device)
        flip = torch.rand(config.batch, generator=generator, device=device) < 0.5
        mix = None
        if config.mix_lights > 0:  # no extra draws without it: runs before it resume exactly
            mix = light_mix(config.batch, config.mix_lights, generator, device)
        colours = None
        if config.permute_colours:  # likewise
            colours = torch.argsort(torch.rand(config.batch, 3, generator=generator, device=device), dim=1)
        if config.crop > 0:  # likewise
            items = crop_items(full, pack, indices, crop_draws(config.batch, config.crop, config.crop_min,
                                                                generator, device))
            batch = make_batch(items, tokenizer, torch.arange(config.batch, device=device), target, flip, mix,
                               colours)
        else:
            batch = make_batch(pack, tokenizer, indices, target, flip, mix, colours)
        example = make_example(batch["input"], batch["relit"], batch["albedo"], batch["lighting"],
                               config.recipe, generator)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=autocast):
            loss, _ = denoising_loss(net, example, config.recipe, generator)
        (loss / config.accumulate).backward()
        return loss.detach()

    while True:
        elapsed = time.time() - train_started
        if elapsed > budget:
            break
        progress = elapsed / budget
        lr = config.lr * min(1.0, (step + 1) / config.warmup)
        lr *= config.min_lr_fraction + (1 - config.min_lr_fraction) * 0.5 * (1 + math.cos(math.pi * progress))
        for group in optimizer.param_groups:
            group["lr"] = lr
        optimizer.zero_grad(set_to_none=True)
        try:
            loss = micro_step()
            for _ in range(config.accumulate - 1):  # the gradient of accumulate × batch items, one step
                loss = loss + micro_step()
            loss = loss / config.accumulate
        except Exception as exc:  # a compiler failure costs one step, not the run
            if net is dit:
                raise
            write(event="compile-failed", step=step, error=repr(exc)[:500])
            net = dit
            continue
        grad_norm = torch.nn.utils.clip_grad_norm_(dit.parameters(), config.grad_clip)
        optimizer.step()
        ema.update(dit, step)
        step += 1
        losses.append(loss)
        if step % config.log_every == 0:
            mean = float(torch.stack(losses).mean())
            losses = []
            if not math.isfinite(mean):
                raise FloatingPointError(f"non-finite loss at step {step}; lower the learning rate")
            memory = ({"gpu_peak_gib": round(torch.cuda.max_memory_allocated(device) / 2 ** 30, 2)}
                      if device.type == "cuda" else {})      # what a batch takes: sizes the next round's
            write(step=step, loss=round(mean, 5), lr=lr, grad_norm=round(float(grad_norm), 4),
                  seconds=round(time.time() - train_started, 1), **memory)
        if time.time() - last_checkpoint > config.checkpoint_every_minutes * 60:
            save_checkpoint()
            last_checkpoint = time.time()
        if val is not None and time.time() - last_val > config.val_every_minutes * 60:
            validate()
            last_val = time.time()
        if time.time() - last_export > config.export_every_minutes * 60:
            export(out, ema.copy_to(ema_model), config, size, lighting_size, {**notes, "steps": step})
            last_export = time.time()
    if val is not None and validated != step and best.get("step") != step:
        validate()
    save_checkpoint()  # a later run on the same --out with more --minutes continues from here
    train_seconds = time.time() - train_started
    ema.copy_to(ema_model).eval()
    if val is not None:  # export the best EMA the validation scenes saw, not necessarily the last
        ema_model.load_state_dict(best["state"])
        notes["selected"] = {"step": best["step"], "val": best["scores"], "val_items": min(config.val_items,
                                                                                         len(val["rgb"]))}
    residual = config.recipe.residual
    quality = {"train": sampled_quality(ema_model, pack, tokenizer, config.eval_items, config.eval_steps, autocast,
                                        residual)}
    if test is not None:
        quality["test"] = sampled_quality(ema_model, test, tokenizer, config.eval_items, config.eval_steps,
                                          autocast, residual)
    summary = {"steps": step, "train_items": n, "train_seconds": round(train_seconds, 1),
               "samples_seen": step * config.batch * config.accumulate, "device": str(device), "params": params,
               "sampled_psnr": quality,
               "date": datetime.datetime.now(datetime.timezone.utc).strftime("%Y-%m-%d %H:%M UTC")}
    if val is not None:
        summary["selected"] = notes["selected"]
    write(event="end", **summary)
    (out / "samples.json").write_text(json.dumps(quality, indent=1))
    export(out, ema_model, config, size, lighting_size, {**notes, **summary},
           config.model_dir or out / "model")
    return summary


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--pack", type=Path, nargs="+", required=True,
                        help="one pack, or several (e.g. different dataset seeds) trained as one")
    parser.add_argument("--test-pack", type=Path)
    parser.add_argument("--val-pack", type=Path,
                        help="held-out scenes: export the EMA (of those at step 0, every --val-every-minutes and "
                             "the end) with the best sampled relit + albedo PSNR on them")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--init", type=Path)
    parser.add_argument("--model-dir", type=Path)
    parser.add_argument("--compile", action="store_true")
    parser.add_argument("--zero-head", action="store_true", help="zero the output layer after --init")
    parser.add_argument("--residual", action="store_true",
                        help="train relit/albedo as offsets from the input (ModelSpec.residual)")
    parser.add_argument("--train-size", type=int, default=None,
                        help="train (and export the model) at this image size, the packs shrunk to it (px)")
    parser.add_argument("--p-sigma-max", type=float, default=0.0,
                        help="share of samples trained at σ_max, the one-step sampler's only call")
    parser.add_argument("--mix-lights", type=float, default=0.0,
                        help="share of items relit between mixtures of their scene's two probes (linear light)")
    parser.add_argument("--crop", type=float, default=0.0,
                        help="share of items cut as a zoomed crop of the pack's full-size images (crop_items)")
    parser.add_argument("--crop-min", type=float, default=0.5,
                        help="the smallest crop's side, as a fraction of the frame's (--crop); never below "
                             "--train-size, a crop is not enlarged")
    parser.add_argument("--permute-colours", action="store_true",
                        help="each item's RGB channels in a random one of the six orders, its probe's alike")
    defaults = FastConfig(pack=Path(), out=Path())
    for name in ("minutes", "device", "batch", "accumulate", "lr", "warmup", "ema_decay", "width", "depth", "num_heads",
                 "seed", "log_every", "eval_items", "eval_steps", "export_every_minutes", "export_steps",
                 "checkpoint_every_minutes", "val_every_minutes", "val_items"):
        value = getattr(defaults, name)
        parser.add_argument(f"--{name.replace('_', '-')}", type=type(value), default=value)
    parser.add_argument("--p-mean", type=float, default=defaults.recipe.p_mean)
    parser.add_argument("--p-std", type=float, default=defaults.recipe.p_std)
    parser.add_argument("--albedo-weight", type=float, default=defaults.recipe.clip_weights[2],
                        help="loss weight of the albedo clip (the paper's 0.1)")
    args = vars(parser.parse_args(argv))
    args["pack"] = args["pack"][0] if len(args["pack"]) == 1 else tuple(args["pack"])
    if args["accumulate"] < 1 or args["batch"] < 1:
        parser.error(f"--batch and --accumulate are counts of at least 1; got {args['batch']} and {args['accumulate']}")
    if not 0 <= args["mix_lights"] <= 1:
        parser.error(f"--mix-lights is a share of items, from 0 to 1; got {args['mix_lights']}")
    if not 0 <= args["crop"] <= 1 or not 0 < args["crop_min"] <= 1:
        parser.error(f"--crop is a share of items from 0 to 1 and --crop-min a fraction of the frame in (0, 1]; "
                     f"got {args['crop']} and {args['crop_min']}")
    if args["crop"] > 0 and args["train_size"] is None:
        parser.error("--crop zooms into the packs' full-size images, so it needs a smaller --train-size")
    recipe = replace(defaults.recipe, p_mean=args.pop("p_mean"), p_std=args.pop("p_std"),
                     clip_weights=(0.0, 1.0, args.pop("albedo_weight")), residual=args.pop("residual"),
                     p_sigma_max=args.pop("p_sigma_max"))
    packs = args["pack"] if isinstance(args["pack"], tuple) else (args["pack"],)
    for path in packs + tuple(args[k] for k in ("test_pack", "val_pack") if args[k]):
        if not path.is_file():
            parser.error(f"no pack at {path}; make one with python -m relight_core.training.pack")
    try:
        summary = train(FastConfig(**args, recipe=recipe))
    except (PackMismatch, InputError) as error:  # packs that do not match; a device this machine lacks
        parser.error(str(error))
    print(json.dumps(summary, indent=1))


if __name__ == "__main__":
    main()
