"""Train a pixel model's detail refiner (relight_core/refiner.py) on its frozen DiT's outputs.

    python -m relight_core.training.refine --model models/default --pack train.npz --seen trained-on.npz \
        --scenes 3000 --val-pack val.npz --out runs/refine --minutes 40 --model-dir models/refined

1. **The DiT's outputs.** The model's one-step relit and albedo frames, as `Relighter` decodes them (its
   residual gains applied, its `shift_average` copies averaged), for both directions of the first
   `--scenes` scenes of the packs that no `--seen` pack holds (scenes the DiT never trained on, so that its
   errors are those it makes on new photos), and for the validation pack. They are the slow part (~0.25 s
   an item on one CPU thread and copy) and are kept in `--out/outputs-*.npz`, so a rerun does not repeat
   them, and a run given more `--scenes` computes only the new ones (a file made with another number of
   copies is refused). `--same-scenes N` adds, for the first N of those scenes and for every validation
   scene, one item relit to the light it was taken under (the input is the target): a refiner that sees the
   light learns to leave a photo alone under its own light, which the probe-following margin measures
   (evaluation.harness).
2. **Training.** The refiner learns a correction of those frames towards the rendered truth: per
   item the log of the squared error after the evaluation protocol's per-channel scale fit, plus half
   the log of the plain squared error, on the foreground mask, relit and albedo alike (or the `--clips`
   named: a refiner may correct the albedo alone, the relit frames staying the filter's); left↔right
   flips; AdamW with a warm-up; an EMA of the weights. Every `--val-every-minutes` the EMA is scored
   on the validation pack by the protocol's PSNR (evaluation.metrics) and the best one is kept.
   `--device cuda` makes the DiT's outputs and trains on a GPU (a GPU round's last minutes, after the DiT
   changed: scripts/gpu_refine.sh); the random draws stay on the CPU and the items in host memory.
3. **Stop and resume.** A checkpoint (weights, EMA, optimiser, generator, step, time used) is written
   at every validation; the same command resumes from it exactly and stops when `--minutes` are used
   (a different `--lr` or `--clips` applies from there). `--init refiner.safetensors` starts a new run
   folder from a refiner trained before (weights and EMA; a new optimiser and step count): one of the
   same shape, or one with a level fewer, grown into this shape with the same output (`grown_state`),
   or one with fewer residual blocks a level, deepened likewise (`deepened_state`);
   one without the light into one with `--lighting` (its FiLM starts at zero); `--zero-head` starts
   the corrected clips' correction at zero (from a refiner trained for the other clip).
4. **The light.** With `--lighting` the refiner sees the target's camera-frame probe (the pack's
   lighting grid, `refiner.light_features`), flipped with its item and its colours permuted alike.

The best refiner (the `--init` one counts, at step 0) goes to `--out/refiner.safetensors` (scores in
`--out/best.json`); `--refit` fits a model folder's own refiner again after its DiT changed; `--model-dir`
also writes a model folder: the model's config.json, DiT and refiners with this one added in `--slot`
("refiner", or "relit_refiner" for a second one beside the model's).
"""

from __future__ import annotations

import argparse
import copy
import json
import os
import shutil
import time
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file, save_file

from relight_core.checkpoint import CONFIG_FILE, DIT_FILE, load_model, resolve_model
from relight_core.colour import permute_colours
from relight_core.devices import resolve_device
from relight_core.evaluation.metrics import protocol_psnr
from relight_core.pipeline import copies_mean, copy_shifts
from relight_core.precision import resolve_precision
from relight_core.refiner import (LIGHT_FEATURES, REFINER_FILE, REFINER_SLOTS, TRANSPORT_LAYERS, Refiner, RefinerConfig,
                                  network_input)
from relight_core.tokenizer import build_tokenizer
from relight_core.training.fast import make_batch, sample_relight
from relight_core.training.pack import load_packs
from relight_core.training.pieces import pack_names
from relight_core.upsample import smooth_offset

CHECKPOINT_FILE = "checkpoint.pt"


# -- the DiT's outputs ------------------------------------------------------------------------

def unseen_items(names: list[str], seen: list[Path], scenes: int | None, same: int = 0) -> list[tuple[int, int, int]]:
    """(scene index, target light, same) for both directions of the first `scenes` scenes no `seen` pack
    holds (`train` passes the validation pack among them: its scenes never train), then for the first
    `same` of them one item relit to the light it was taken under (same = 1: the input is the scene
    under the target light too, light scene % 2), after them so that a cache of the others stays valid."""
    held = pack_names(seen)
    chosen = [i for i, name in enumerate(names) if str(name) not in held]
    chosen = chosen if scenes is None else chosen[:scenes]
    return [(i, t, 0) for i in chosen for t in (0, 1)] + [(i, i % 2, 1) for i in chosen[:same]]


@torch.no_grad()
def dit_outputs(model: Path, pack: dict, items: list[tuple[int, int, int]], batch: int = 16,
                log=print, copies: int | None = None, device: str | torch.device = "cpu") -> dict[str, np.ndarray]:
    """The model's relit and albedo frames (uint8 [N,3,H,W]) for `items` (`unseen_items`), as `Relighter`
    decodes them: its residual gains applied, and with its `shift_average` (or `copies`) copies the mean of
    the copies run on the input rolled by half a DiT token (`pipeline.copies_mean`); an item with same = 1
    has the scene under the target light as its input too. The DiT runs on `device` (the pack stays where
    it is; each batch goes over), in bf16 where that device computes it faster."""
    device = torch.device(device)
    spec, dit, _ = load_model(model, device)
    if spec.tokenizer.get("type") != "pixel" or not spec.residual:
        raise ValueError(f"{model} is not a residual pixel-tokenizer model; the refiner is for the default model's kind")
    tokenizer = build_tokenizer(spec.tokenizer)
    token = tokenizer.spatial_factor * spec.dit.patch_spatial
    variants = [(False, shift) for shift in copy_shifts(copies or spec.shift_average, token)]
    autocast = resolve_precision("auto", device) == torch.bfloat16
    relit, albedo = [], []
    started = time.time()
    start, batches = 0, 0
    while start < len(items):
        part = items[start:start + batch]
        kinds = [same for _, _, same in part]
        if len(set(kinds)) > 1:                                     # one kind a batch: cut at the change
            part = part[:kinds.index(1 - kinds[0])]
        scenes = torch.tensor([s for s, _, _ in part])
        targets = torch.tensor([t for _, t, _ in part])
        mix = torch.ones(len(part), 2) if part[0][2] else None       # make_batch: the input under the target light
        data = make_batch(pack, tokenizer, scenes, targets, torch.zeros(len(part), dtype=torch.bool), mix)
        data = {key: value.to(device) for key, value in data.items()}
        source = tokenizer.decode(data["input"]).float()              # [B,3,t,H,W]
        t = data["input"].shape[2]
        entries = {1: [], 2: []}
        # each copy on the same noise (Relighter draws each its own; the one step from σ 80 barely depends on
        # it: runs/shift-average/seeds.py); the light stays where it is, as a half-token shift does not turn it
        for _, shift in variants:
            inputs = source.roll(shift, dims=(-2, -1))
            x0 = sample_relight(dit, {**data, "input": tokenizer.encode(inputs)}, spec.steps, autocast=autocast,
                                residual=True, final_denoise=spec.final_denoise)
            for clip, gain in ((1, spec.residual_gain[0]), (2, spec.residual_gain[1])):
                frames = tokenizer.decode(x0[:, :, clip * t:(clip + 1) * t].float())[:, :, 0]
                # the gain Relighter's denoiser applies at each call of a one-step run: once where the
                # schedule ends at 0, twice with the clean-up call at σ_min (ModelSpec.final_denoise)
                gain = gain ** 2 if spec.final_denoise else gain
                frames = inputs[:, :, 0] + gain * (frames - inputs[:, :, 0])
                entries[clip].append(frames.clamp(-1, 1).permute(0, 2, 3, 1).cpu().numpy())
        for clip, out in ((1, relit), (2, albedo)):
            mean = torch.from_numpy(np.ascontiguousarray(copies_mean(np.stack(entries[clip]), variants, token)))
            out.append(((mean.permute(0, 3, 1, 2) + 1) * 127.5).round().to(torch.uint8).numpy())
        if batches % 25 == 0:
            log(f"DiT outputs: {start + len(part)} of {len(items)} items, {time.time() - started:.0f} s")
        start, batches = start + len(part), batches + 1
    return {"relit": np.concatenate(relit), "albedo": np.concatenate(albedo)}


def item_keys(pack: dict, items: list[tuple[int, int, int]]) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """What an outputs file names its items by: scene names, target lights and same (int64)."""
    return (np.array([str(pack["names"][s]) for s, _, _ in items]), np.array([t for _, t, _ in items]),
            np.array([k for _, _, k in items], dtype=np.int64))


def file_keys(z) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """`item_keys` of the items an open outputs file (np.load) holds; files written before `same` existed hold none."""
    same = z["same"] if "same" in z.files else np.zeros(len(z["names"]), np.int64)
    return z["names"], z["targets"], same


def held_rows(path: Path, names: np.ndarray, targets: np.ndarray, same: np.ndarray) -> list[int | None]:
    """For each item (`item_keys`), its row in the outputs file `path`, or None where the file lacks it."""
    with np.load(path, allow_pickle=False) as z:
        where = {(str(n), int(t), int(k)): i for i, (n, t, k) in enumerate(zip(*file_keys(z)))}
    return [where.get((str(n), int(t), int(k))) for n, t, k in zip(names, targets, same)]


def held_frames(path: Path, rows: list[int | None]) -> dict[str, np.ndarray] | None:
    """uint8 relit and albedo frames for the items `rows` (`held_rows`) points to, read from `path`; the
    rows of the items it lacks are left to fill. None when it holds none of them."""
    hits = [i for i, r in enumerate(rows) if r is not None]
    if not hits:
        return None
    with np.load(path, allow_pickle=False) as z:
        out = {k: np.empty((len(rows), *z[k].shape[1:]), np.uint8) for k in ("relit", "albedo")}
        for key, frames in out.items():
            frames[hits] = z[key][[rows[i] for i in hits]]
    return out


def cached_outputs(path: Path, model: Path, pack: dict, items: list[tuple[int, int, int]], log=print,
                   copies: int | None = None, device: str | torch.device = "cpu") -> dict:
    """`dit_outputs` for `items`, kept in `path`: the items it holds already (by scene name, direction and
    same) are read from it, only the others are computed, and the file is rewritten with all of them in order.
    The file records how many shifted copies made them (`copies`, else the model's `shift_average`; a file
    without the record holds one-copy outputs): one made with another count is refused, not mixed in."""
    copies = copies or resolve_model(model)[0].shift_average
    names, targets, same = item_keys(pack, items)
    out, missing = None, list(range(len(items)))
    if path.is_file():
        with np.load(path, allow_pickle=False) as z:
            held = int(z["copies"]) if "copies" in z.files else 1
            if held != copies:
                raise ValueError(f"{path} holds the DiT's outputs averaged over {held} shifted copies and this model "
                                 f"runs {copies} (its shift_average): give the run a new --out")
            if all(np.array_equal(a, b) for a, b in zip(file_keys(z), (names, targets, same))):
                return {"relit": z["relit"], "albedo": z["albedo"]}
        rows = held_rows(path, names, targets, same)
        missing = [i for i, r in enumerate(rows) if r is None]
        out = held_frames(path, rows)
        log(f"{path} holds {len(items) - len(missing)} of these {len(items)} items; computing the other {len(missing)}")
    if missing:
        fresh = dit_outputs(model, pack, [items[i] for i in missing], log=log, copies=copies, device=device)
        if out is None:
            out = fresh
        else:
            for key, frames in out.items():
                frames[missing] = fresh[key]
    np.savez(path, names=names, targets=targets, same=same, copies=np.int64(copies), **out)
    return out


def item_tensors(pack: dict, items: list[tuple[int, int, int]], outputs: dict, spec, base: str,
                 device: str | torch.device | None = None) -> dict:
    """uint8 tensors per item: input, target, albedo_t, relit, albedo (the DiT's), mask; env, the target's
    camera-frame probe on the pack's lighting grid (float32 [N,s,s,3]); for base "filtered" also f_relit,
    f_albedo (after the model's offset filter, as `Relighter._smoothed`); same, True where the input is the
    scene under the target light too. The filter runs where OpenCV's does, or in torch on `device` where this
    OpenCV has no ximgproc (`upsample.guided_filter`)."""
    scenes = torch.tensor([s for s, _, _ in items])
    targets = torch.tensor([t for _, t, _ in items])
    same = torch.tensor([bool(k) for _, _, k in items])
    data = {"input": pack["rgb"][scenes, torch.where(same, targets, 1 - targets)], "target": pack["rgb"][scenes, targets],
            "same": same,
            "albedo_t": pack["albedo"][scenes], "mask": pack["mask"][scenes],
            "env": torch.as_tensor(pack["env"])[scenes, targets].float().contiguous(),
            "relit": torch.from_numpy(outputs["relit"]), "albedo": torch.from_numpy(outputs["albedo"])}
    if base == "filtered":
        radii = spec.offset_filter
        filtered = {"f_relit": [], "f_albedo": []}
        for start in range(0, len(items), 256):
            guide = _hwc(data["input"][start:start + 256])
            for key, source, radius in (("f_relit", "relit", radii[0]), ("f_albedo", "albedo", radii[1])):
                frames = smooth_offset(guide, _hwc(data[source][start:start + 256]), radius, device=device)
                filtered[key].append(torch.from_numpy(np.round(frames * 255).astype(np.uint8)).permute(0, 3, 1, 2))
        data.update({k: torch.cat(v).contiguous() for k, v in filtered.items()})
    return data


def input_floors(data: dict) -> torch.Tensor:
    """[N] the protocol's PSNR of each item's input against its target (the floor: how little the new light
    changes the scene; `evaluation.metrics.protocol_psnr`)."""
    floors = []
    for start in range(0, len(data["input"]), 256):
        part = slice(start, start + 256)
        inputs, targets, masks = _hwc(data["input"][part]), _hwc(data["target"][part]), data["mask"][part].numpy()
        floors += [protocol_psnr(inputs[i:i + 1], targets[i:i + 1], masks[i:i + 1]) for i in range(len(masks))]
    return torch.tensor(floors)


def _hwc(images: torch.Tensor) -> np.ndarray:
    """uint8 [N,3,H,W] → float32 [N,H,W,3] in [0, 1]."""
    return images.permute(0, 2, 3, 1).numpy().astype(np.float32) / 255


def _signed(images: torch.Tensor) -> torch.Tensor:
    return images.float() / 127.5 - 1


# -- training ---------------------------------------------------------------------------------

def item_loss(pred: torch.Tensor, target: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """Mean over items of log MSE after a per-channel scale fit on the mask + ½ log plain MSE
    (images [B,3,H,W] in [-1, 1], mask [B,H,W]): the protocol's PSNR, as a loss."""
    p, t = (pred + 1) / 2, (target + 1) / 2
    m = mask[:, None].float()
    count = m.sum((1, 2, 3)).clamp_min(1) * 3
    plain = (m * (p - t) ** 2).sum((1, 2, 3)) / count
    scale = (m * p * t).sum((2, 3)) / (m * p * p).sum((2, 3)).clamp_min(1e-6)
    fitted = (m * (p * scale[..., None, None] - t) ** 2).sum((1, 2, 3)) / count
    return torch.log(fitted + 1e-5).mean() + 0.5 * torch.log(plain + 1e-5).mean()


def model_inputs(data: dict, index, base: str, flip: torch.Tensor | None = None, device: torch.device | None = None):
    """(network input [B,9|15,H,W], relit base, albedo base) in [-1, 1] for items `index`, and `get`, which
    reads any other of their tensors (flipped alike: images and masks along x, the probe env u → 1 − u), all
    on `device` (None: where `data` is)."""
    flips = flip if flip is None or device is None else flip.to(device)

    def get(key):
        x = data[key][index]
        if device is not None:
            x = x.to(device, non_blocking=True)
        if flips is not None:
            axis = 2 if key == "env" else -1    # env [B,s,s,3]: the panorama's u axis
            x = torch.where(flips.view(-1, *([1] * (x.dim() - 1))), x.flip(axis), x)
        return x

    filtered = (_signed(get("f_relit")), _signed(get("f_albedo"))) if base == "filtered" else None
    return (*network_input(base, *(_signed(get(k)) for k in ("input", "relit", "albedo")), filtered), get)


@torch.no_grad()
def validate(refiner: Refiner, data: dict, autocast: bool) -> dict[str, float]:
    """The protocol's mean PSNR (relit, albedo) of the refined frames on `data`, as `Relighter` makes them
    (a clip the refiner does not correct is scored as its base); the refiner runs on the device it is on."""
    device = next(refiner.parameters()).device
    relit, albedo = [], []
    for start in range(0, len(data["input"]), 32):
        index = slice(start, start + 32)
        x, r, a, get = model_inputs(data, index, refiner.config.base, device=device)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=autocast):
            delta = refiner.correction(x.contiguous(memory_format=torch.channels_last),
                                       get("env") if refiner.config.lighting else None).float()
        r, a = refiner.corrected(delta, r, a, inputs=x[:, :3])
        relit.append(((r + 1) / 2).cpu())
        albedo.append(((a + 1) / 2).cpu())
    return scores(data, torch.cat(relit).permute(0, 2, 3, 1).numpy(), torch.cat(albedo).permute(0, 2, 3, 1).numpy())


def scores(data: dict, relit: np.ndarray, albedo: np.ndarray) -> dict[str, float]:
    """The protocol's mean PSNR: relit over the items relit to another light, albedo over all; where there
    are items relit to their own light, "same" (their relit PSNR: reported, not what the best is chosen by)."""
    target, albedo_t, mask = _hwc(data["target"]), _hwc(data["albedo_t"]), data["mask"].numpy()
    same = data["same"].numpy() if "same" in data else np.zeros(len(mask), bool)
    relit_psnr = np.array([protocol_psnr(relit[i], target[i], mask[i]) for i in range(len(mask))])
    out = {"relit": round(float(relit_psnr[~same].mean()), 3),
           "albedo": round(float(np.mean([protocol_psnr(albedo[i], albedo_t[i], mask[i]) for i in range(len(mask))])), 3)}
    if same.any():
        out["same"] = round(float(relit_psnr[same].mean()), 3)
    return out


def train(args: argparse.Namespace, log=print) -> dict:
    """Run (or resume) a refiner training; returns best.json's contents."""
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(args.threads)
    device = resolve_device(args.device)
    spec, _, _ = load_model(args.model, "cpu")
    config = flag_config(args)
    pack = load_packs(args.pack)
    if len(set(map(str, pack["names"]))) < len(pack["names"]):
        raise ValueError("the --pack files hold scenes of the same name (two render-data runs' scene_000000, say), "
                         "and the DiT's outputs are kept by name; train on one render's packs at a time")
    items = unseen_items(pack["names"], [*args.seen, args.val_pack], args.scenes, args.same_scenes)
    if not items:
        raise ValueError("no scene of the packs is left once the --seen packs' scenes are taken out")
    outputs = cached_outputs(out / "outputs-train.npz", args.model, pack, items, log, device=device)
    train_data = item_tensors(pack, items, outputs, spec, config.base, device)
    del pack
    val_pack = load_packs(args.val_pack)
    val_items = unseen_items(val_pack["names"], [], None, len(val_pack["names"]) if args.same_scenes else 0)
    val_outputs = cached_outputs(out / "outputs-val.npz", args.model, val_pack, val_items, log, device=device)
    val_data = item_tensors(val_pack, val_items, val_outputs, spec, config.base, device)
    del val_pack
    autocast = resolve_precision("auto", device) == torch.bfloat16

    model = Refiner(config).to(device, memory_format=torch.channels_last)   # ~1.4× faster convolutions on a CPU
    ema = copy.deepcopy(model).eval().requires_grad_(False)
    optimizer = refiner_optimizer(model, args.lr, args.head_lr, transport_lr=args.transport_lr)
    generator = torch.Generator().manual_seed(args.seed)
    state = {"step": 0, "seconds": 0.0, "best": None,
             "start": {"dit": scores(val_data, _hwc(val_data["relit"]), _hwc(val_data["albedo"]))}}
    if config.base == "filtered":
        state["start"]["filtered"] = scores(val_data, _hwc(val_data["f_relit"]), _hwc(val_data["f_albedo"]))
    checkpoint = out / CHECKPOINT_FILE
    if checkpoint.is_file():
        saved = torch.load(checkpoint, map_location=device, weights_only=True)
        if RefinerConfig.from_dict(saved["config"]).shape != config.shape:
            raise ValueError(f"{checkpoint} is a refiner of another shape ({saved['config']}); "
                             "give a new --out or the same --widths/--blocks/--base/--lighting/--input-mix/"
                             "--light-detail/--film-encoder/--transport/--reshade")
        model.load_state_dict(saved["model"])
        ema.load_state_dict(saved["ema"])
        optimizer = refiner_optimizer(model, args.lr, args.head_lr, saved["optimizer"], args.transport_lr)
        generator.set_state(saved["generator"].cpu())
        state = json.loads(saved["state"])
        log(f"resumed at step {state['step']} ({state['seconds'] / 60:.1f} min used)"
            + (f"; --init {args.init} is for a new run folder and is not used" if args.init is not None else ""))
    else:
        if args.init is not None:
            how = initial_weights(model, args.init)
            if args.zero_head:
                with torch.no_grad():
                    for k, clip in enumerate(("relit", "albedo")):
                        if clip in config.clips:
                            model.head.weight[3 * k:3 * k + 3] = 0
                            model.head.bias[3 * k:3 * k + 3] = 0
                    model.head.weight[6:] = 0       # the input mix's channels (input_mix), if any
                    model.head.bias[6:] = 0
                how += "; the corrected clips' head set to zero"
            ema.load_state_dict(model.state_dict())
            state["start"]["init"] = validate(ema, val_data, autocast)   # what the run must beat
            log(f"starting from the refiner in {args.init}, {how} (a new optimiser)")
        log(f"start (the DiT's frames on the validation pack): {state['start']}")
    records = open(out / "log.jsonl", "a")

    def save_best(score: dict) -> None:
        # each file written aside and renamed: a run stopped at any moment (a GPU call's time limit) leaves the best
        # EMA so far whole, never a cut-off file
        partial = out / (REFINER_FILE + ".partial")
        save_file({k: v.detach().cpu().contiguous() for k, v in ema.state_dict().items()}, partial)
        os.replace(partial, out / REFINER_FILE)
        kept = [*config.clips, *(["same"] if "same" in score and "relit" in config.clips else [])]
        best = {"step": state["step"], "val": {k: score[k] for k in kept}, "start": state["start"],
                "refiner": config.to_dict(),
                "model": str(args.model), "train_items": len(items), "val_items": len(val_items)}
        (out / "best.json.partial").write_text(json.dumps(best, indent=1))
        os.replace(out / "best.json.partial", out / "best.json")
        state["best"] = score

    if state["best"] is None and "init" in state["start"]:
        save_best(state["start"]["init"])    # the refiner it starts from is the one to beat, and kept if none does

    count = len(train_data["input"])
    weights = None
    if args.alike_weight != 1.0:       # items the new light changes little (a high floor), drawn more often
        alike = (input_floors(train_data) >= args.alike_db) & ~train_data["same"]   # not the --same-scenes items
        weights = torch.where(alike, args.alike_weight, 1.0)
        log(f"{int(alike.sum())} of {count} items have a floor of {args.alike_db} dB or more; drawn "
            f"{args.alike_weight}× as often")
    since_val, started = 0.0, time.time() - state["seconds"]
    while state["seconds"] < args.minutes * 60:
        step_started = time.time()
        index = (torch.randint(0, count, (args.batch,), generator=generator) if weights is None
                 else torch.multinomial(weights, args.batch, replacement=True, generator=generator))
        flip = torch.rand(args.batch, generator=generator) < 0.5
        x, r, a, get = model_inputs(train_data, index, config.base, flip, device)
        targets = {"relit": _signed(get("target")), "albedo": _signed(get("albedo_t"))}
        env = get("env")
        if args.permute_colours:
            order = torch.argsort(torch.rand(args.batch, 3, generator=generator), dim=1).to(device)
            x, r, a = (permute_colours(t, order) for t in (x, r, a))
            targets = {k: permute_colours(t, order) for k, t in targets.items()}
            env = permute_colours(env, order, dim=-1)                           # the light's colours alike
        for group in optimizer.param_groups:
            group["lr"] = args.lr * group["scale"] * min(1.0, (state["step"] + 1) / args.warmup)
        with torch.autocast(device.type, dtype=torch.bfloat16, enabled=autocast):
            delta = model(x.contiguous(memory_format=torch.channels_last),
                          model.light(env) if config.lighting else None).float()
        mask = get("mask")
        refined = dict(zip(("relit", "albedo"), model.corrected(delta, r, a, clamp=False, inputs=x[:, :3])))
        loss = sum(item_loss(refined[clip], targets[clip], mask) for clip in config.clips)
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        optimizer.step()
        with torch.no_grad():
            for e, p in zip(ema.parameters(), model.parameters()):
                e.lerp_(p, 1 - args.ema)
        state["step"] += 1
        state["seconds"] = time.time() - started
        since_val += time.time() - step_started
        if state["step"] % 50 == 0:
            log(f"step {state['step']} loss {loss.item():.4f} {state['seconds'] / 60:.1f} min")
        if since_val >= args.val_every_minutes * 60 or state["seconds"] >= args.minutes * 60:
            since_val = 0.0
            score = validate(ema, val_data, autocast)
            records.write(json.dumps({"step": state["step"], "minutes": round(state["seconds"] / 60, 2),
                                      "loss": round(loss.item(), 4), "val": score}) + "\n")
            records.flush()
            log(f"step {state['step']}: validation {score}")
            if state["best"] is None or sum(score[c] for c in config.clips) > sum(state["best"][c] for c in config.clips):
                save_best(score)
            torch.save({"model": model.state_dict(), "ema": ema.state_dict(), "optimizer": optimizer.state_dict(),
                        "generator": generator.get_state(), "config": config.to_dict(),
                        "state": json.dumps(state)}, checkpoint)
    records.close()
    if not (out / REFINER_FILE).is_file():
        raise ValueError("no validation ran, so no refiner was kept; give more --minutes")
    best = json.loads((out / "best.json").read_text())
    if args.model_dir is not None:
        write_model(Path(args.model), out, Path(args.model_dir), best, args.slot)
    return best


SHAPE_FLAGS = ("widths", "blocks", "base", "clips", "flip_average", "lighting", "relit_gain", "input_mix",
               "light_detail", "film_encoder", "transport", "reshade")


def refit_flags(args: argparse.Namespace) -> None:
    """`--refit`: set the shape flags (`SHAPE_FLAGS`) from the refiner `args.model`'s config.json has in `args.slot`,
    and `--init` (unless given) to that refiner's weights, so that the run fits the model's own refiner again to
    what its DiT now makes. ValueError in one sentence where the model has no refiner there."""
    path = Path(args.model) / CONFIG_FILE
    try:
        entry = json.loads(path.read_text()).get(args.slot)
    except (OSError, ValueError) as exc:
        raise ValueError(f"--refit reads the refiner from {path}, which cannot be read ({exc})") from None
    if not entry:
        raise ValueError(f"--refit: {path} names no refiner in \"{args.slot}\"; give --slot the one it has, or the "
                         "shape flags without --refit")
    config = RefinerConfig.from_dict(entry)
    for flag in SHAPE_FLAGS:
        value = getattr(config, flag)
        setattr(args, flag, list(value) if isinstance(value, tuple) else value)
    if args.init is None:
        args.init = Path(args.model) / REFINER_SLOTS[args.slot]


def flag_config(args: argparse.Namespace) -> RefinerConfig:
    """The refiner the flags describe (strength 1: training always uses it), checked by `RefinerConfig.from_dict`."""
    return RefinerConfig.from_dict({"widths": args.widths, "blocks": args.blocks, "base": args.base, "clips": args.clips,
                                    "flip_average": args.flip_average, "lighting": args.lighting,
                                    "relit_gain": args.relit_gain, "input_mix": args.input_mix,
                                    "light_detail": args.light_detail, "film_encoder": args.film_encoder,
                                    "transport": args.transport, "reshade": args.reshade})


def refiner_optimizer(model: Refiner, lr: float, head_lr: float = 1.0, saved: dict | None = None,
                      transport_lr: float = 1.0) -> torch.optim.AdamW:
    """AdamW over `model`'s weights, its last layer (`head`) at `head_lr` times `lr` and its transport layer
    (`transport_head` and `transport_gate`, if any: new, from zero, beside trained weights) at `transport_lr`
    times: each group's "scale", which the warm-up multiplies in. With `saved` (a checkpoint's optimiser state) it resumes that
    one, its scales as they were; one saved before the head had a group of its own resumes as its one group."""
    if saved is not None and len(saved["param_groups"]) == 1:
        groups = [{"params": list(model.parameters()), "scale": 1.0}]
    else:
        named = list(model.named_parameters())
        head = [p for name, p in named if name.startswith("head.")]
        transport = [p for name, p in named if name.startswith(TRANSPORT_LAYERS)]
        rest = [p for name, p in named if not name.startswith(("head.", *TRANSPORT_LAYERS))]
        groups = [{"params": rest, "scale": 1.0}, {"params": head, "scale": head_lr}]
        if transport:
            groups.append({"params": transport, "scale": transport_lr})
    optimizer = torch.optim.AdamW(groups, lr=lr, weight_decay=0.0)
    if saved is not None:
        optimizer.load_state_dict(saved)
        for group in optimizer.param_groups:
            group.setdefault("scale", 1.0)
    return optimizer


def initial_weights(refiner: Refiner, path: Path) -> str:
    """Load `--init`'s refiner weights (safetensors) into `refiner`, or fail in one sentence. A refiner of
    the same shape loads as it is; one with a level fewer (the same widths but the last, blocks and base)
    is grown into this one (`grown_state`), giving the same output. Returns which it was."""
    try:
        state = load_file(str(path), device=str(next(refiner.parameters()).device))    # beside the fresh weights
    except Exception as exc:  # safetensors raises its own error types for corrupt headers
        raise ValueError(f"--init {path} is not a readable safetensors file ({exc})") from exc
    lit = ""
    fresh = refiner.state_dict()
    if refiner.config.lighting and not any(key.startswith("film.") for key in state):
        # a refiner without the light: it gains the FiLM, which starts at zero (the same output)
        state = {**state, **{k: v for k, v in fresh.items() if k.startswith("film.")}}
        lit = ", with the light's FiLM new"
    head = state.get("head.weight")
    if refiner.config.input_mix and head is not None and head.shape[0] == 6:
        # a refiner without the input mix: its head gains the mix's channels, at zero (the input's weight
        # starts at sigmoid(−5), the output nearly the same)
        state = {**state, "head.weight": torch.cat([head, fresh["head.weight"][6:]]),
                 "head.bias": torch.cat([state["head.bias"], fresh["head.bias"][6:]])}
        lit += ", with the input mix new"
    widened = widened_film(state, refiner, fresh)
    if widened is not None:
        state = widened
        lit += ", with more of the light new (at zero weight)"
    if refiner.config.transport and "transport_head.weight" not in state:
        # a refiner without the transport term gains it at zero: a uniform weighting, a shading of 1 (a gate of 0)
        state = {**state, **{k: v for k, v in fresh.items() if k.startswith(TRANSPORT_LAYERS)}}
        lit += ", with the transport term new (at zero)"
    try:
        refiner.load_state_dict(state)
        return "as it is" + lit
    except RuntimeError:
        pass
    try:
        refiner.load_state_dict(grown_state(state, refiner))
        return f"grown by a level ({refiner.config.widths[-1]} channels at 1/{2 ** (len(refiner.config.widths) - 1)} size){lit}"
    except (RuntimeError, KeyError, ValueError):
        pass
    try:
        refiner.load_state_dict(deepened_state(state, refiner))
        return f"deepened to {refiner.config.blocks} residual blocks a level{lit}"
    except (RuntimeError, KeyError, ValueError) as exc:
        raise ValueError(f"--init {path} is not a refiner of this shape nor one with a level fewer or fewer blocks; "
                         "give the --widths, --blocks and --base it was trained with (or those plus one more width, "
                         "or more --blocks)") from exc


def widened_film(state: dict[str, torch.Tensor], refiner: Refiner, fresh: dict[str, torch.Tensor]
                 ) -> dict[str, torch.Tensor] | None:
    """The weights of a refiner that sees less of the light than `refiner` (the 8×8 grid only, and/or no FiLM on
    its encoder), its FiLM widened into `refiner`'s so that the output is unchanged: its weights first, the
    `light_detail` grid's inputs and the encoder's scale and shift rows at zero. None for any other state (one
    that already fits, or one with another fine grid: that is not less of the light, and must not be misread)."""
    film_in, film_out = state.get("film.0.weight"), state.get("film.2.weight")
    if not refiner.config.lighting or film_in is None or film_out is None:
        return None
    full_in, full_out = fresh["film.0.weight"].shape[1], fresh["film.2.weight"].shape[0]
    decoder_rows = 2 * sum(refiner.film_sizes[:len(refiner.config.widths)])    # the middle's and the decoder's
    if (film_in.shape[1] not in (LIGHT_FEATURES, full_in) or film_out.shape[0] not in (decoder_rows, full_out)
            or (film_in.shape[1], film_out.shape[0]) == (full_in, full_out)
            or film_in.shape[0] != fresh["film.0.weight"].shape[0] or film_out.shape[1] != fresh["film.2.weight"].shape[1]):
        return None
    first, last = torch.zeros_like(fresh["film.0.weight"]), torch.zeros_like(fresh["film.2.weight"])
    bias = torch.zeros_like(fresh["film.2.bias"])
    first[:, :film_in.shape[1]] = film_in
    last[:film_out.shape[0]], bias[:film_out.shape[0]] = film_out, state["film.2.bias"]
    return {**state, "film.0.weight": first, "film.2.weight": last, "film.2.bias": bias}


def grown_state(state: dict[str, torch.Tensor], refiner: Refiner) -> dict[str, torch.Tensor]:
    """The weights of a refiner with one level fewer than `refiner`, grown into `refiner`'s shape so that
    its output is unchanged: the old bottom's 2·blocks residual blocks become the new last encoder and
    decoder level (first half, second half), the new bottom (its down-sampling and middle blocks) starts
    fresh, and the new level's 1×1 merge passes the skip through unchanged and gives the new bottom's
    channels zero weight, so they start to count only as training moves that weight."""
    levels, blocks = len(refiner.config.widths), refiner.config.blocks
    fresh = refiner.state_dict()
    if any(f"down.{levels - 2}.{k}" in state or f"up.{levels - 2}.{k}" in state for k in ("weight", "bias")):
        raise ValueError("not a refiner with a level fewer")
    grown = {}
    for key, value in state.items():
        head, _, rest = key.partition(".")
        if head == "mid":
            index, _, tail = rest.partition(".")
            index = int(index)
            grown[f"enc.{levels - 2}.{index}.{tail}" if index < blocks else f"dec.{levels - 2}.{index - blocks}.{tail}"] = value
        else:
            grown[key] = value
    width = refiner.config.widths[-2]
    merge = torch.zeros_like(fresh[f"up.{levels - 2}.weight"])          # [width, next + width, 1, 1]
    merge[:, -width:, 0, 0] = torch.eye(width)                          # the skip passes through
    grown[f"up.{levels - 2}.weight"] = merge
    grown[f"up.{levels - 2}.bias"] = torch.zeros_like(fresh[f"up.{levels - 2}.bias"])
    for key, value in fresh.items():
        if key.startswith(("mid.", f"down.{levels - 2}.")):
            grown[key] = value
    return grown


def deepened_state(state: dict[str, torch.Tensor], refiner: Refiner) -> dict[str, torch.Tensor]:
    """The weights of a refiner with fewer residual blocks a level than `refiner` (the same widths and base),
    deepened into `refiner`'s shape so that its output is unchanged: each level keeps its trained blocks
    first, and the new ones after them start with their second convolution at zero — a residual block
    whose last convolution is zero passes its input through (`_Block`), and its first one, fresh, gives
    that zero convolution a gradient from the first step."""
    fresh = refiner.state_dict()

    def block(key: str) -> int | None:
        """The block index of a residual block's weight (counted over the middle's two halves), else None."""
        head, _, rest = key.partition(".")
        parts = rest.split(".")
        return int(parts[1]) if head in ("enc", "dec") else int(parts[0]) if head == "mid" else None

    old = max((block(key) + 1 for key in state if key.startswith(("enc.", "dec."))), default=0)
    if old >= refiner.config.blocks or any(block(key) is None and key not in state for key in fresh):
        raise ValueError("not a refiner with fewer blocks")
    deepened = dict(fresh)
    for key, value in state.items():
        if key not in fresh or fresh[key].shape != value.shape:
            raise ValueError(f"not a refiner with fewer blocks of this shape ({key})")
        deepened[key] = value
    for key in fresh:
        index = block(key)
        if (index is not None and index >= (2 * old if key.startswith("mid.") else old)
                and key.endswith(("conv2.weight", "conv2.bias"))):
            deepened[key] = torch.zeros_like(fresh[key])
    return deepened


def write_model(model: Path, run: Path, folder: Path, best: dict, slot: str = "refiner") -> Path:
    """A model folder: `model`'s DiT, config.json and refiners with the run's refiner added in `slot`
    ("refiner" or "relit_refiner", `REFINER_SLOTS`; a refiner `model` has in the other slot stays). The
    `grid_shift` of the refiner `model` had in `slot` carries over (how it is run, not trained); its strength
    does not (`training.calibrate --strengths` fits the new one's)."""
    folder.mkdir(parents=True, exist_ok=True)
    config = json.loads((model / CONFIG_FILE).read_text())
    if folder.resolve() != model.resolve():
        shutil.copyfile(model / DIT_FILE, folder / DIT_FILE)
        for other, file in REFINER_SLOTS.items():
            if other != slot and config.get(other) is not None:
                shutil.copyfile(model / file, folder / file)
    shutil.copyfile(run / REFINER_FILE, folder / REFINER_SLOTS[slot])
    shift = (config.get(slot) or {}).get("grid_shift")
    config[slot] = {**best["refiner"], **({"grid_shift": shift} if shift else {})}
    config.setdefault("notes", {})[slot] = {k: best[k] for k in ("step", "val", "start", "train_items", "val_items")}
    (folder / CONFIG_FILE).write_text(json.dumps(config, indent=2) + "\n")
    return folder


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--model", type=Path, required=True, help="a residual pixel-tokenizer model folder")
    parser.add_argument("--pack", type=Path, nargs="+", required=True, help="packs (training.pack) to train on")
    parser.add_argument("--seen", type=Path, nargs="*", default=[], help="packs whose scenes the DiT trained on")
    parser.add_argument("--scenes", type=int, default=None, help="at most this many unseen scenes (both directions each)")
    parser.add_argument("--val-pack", type=Path, required=True, help="held-out scenes to choose the refiner on")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--model-dir", type=Path, help="also write a model folder with the refiner here")
    parser.add_argument("--init", type=Path, help="a new run starts from this refiner.safetensors, of this shape "
                        "or with a level or some blocks fewer (a run that resumes from its checkpoint ignores it)")
    parser.add_argument("--minutes", type=float, default=30.0)
    parser.add_argument("--lr", type=float, default=1.5e-3)
    parser.add_argument("--head-lr", type=float, default=1.0,
                        help="the last layer's learning rate as a multiple of --lr (a new input mix learns faster)")
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--warmup", type=int, default=100)
    parser.add_argument("--ema", type=float, default=0.998)
    parser.add_argument("--widths", type=int, nargs="+", default=list(RefinerConfig.widths))
    parser.add_argument("--blocks", type=int, default=RefinerConfig.blocks)
    parser.add_argument("--base", choices=("raw", "filtered"), default="filtered")
    parser.add_argument("--clips", nargs="+", choices=("relit", "albedo"), default=["relit", "albedo"],
                        help="the frames it learns to correct (its loss, the choice of the best, the model's config)")
    parser.add_argument("--flip-average", action="store_true",
                        help="the refiner averages its correction with the mirror image's (validation and the model's config)")
    parser.add_argument("--same-scenes", type=int, default=0,
                        help="also train on this many scenes relit to their own light (and validate on every validation "
                             "scene so), so that a refiner that sees the light leaves a photo alone under its own light")
    parser.add_argument("--lighting", action="store_true",
                        help="the refiner sees the target light (refiner.light_features through FiLM)")
    parser.add_argument("--light-detail", type=int, default=0, metavar="K",
                        help="with --lighting: the FiLM also sees the probe on a K×K grid (refiner.RefinerConfig.light_detail)")
    parser.add_argument("--film-encoder", action="store_true",
                        help="with --lighting: FiLM on the encoder levels too (refiner.RefinerConfig.film_encoder)")
    parser.add_argument("--transport", type=int, default=0, metavar="K",
                        help="with --lighting and --relit-gain: the relit log gain also gets the log of a shading linear "
                             "in the light, a per-pixel weighted mean of the probe's K×K cells (refiner.RefinerConfig.transport)")
    parser.add_argument("--reshade", action="store_true",
                        help="with --transport: the term, gated per pixel, swaps the base's own shading (relit ÷ albedo) "
                             "for the transport one (refiner.RefinerConfig.reshade)")
    parser.add_argument("--transport-lr", type=float, default=1.0, metavar="F",
                        help="the transport layer (new, from zero) learns F times faster than --lr")
    parser.add_argument("--relit-gain", type=int, default=0, metavar="CELL",
                        help="the relit correction is a smooth gain on the relit base, one value per CELL×CELL pixels "
                             "interpolated (refiner.RefinerConfig.relit_gain): it cannot draw an edge; 0 (default): added")
    parser.add_argument("--input-mix", action="store_true",
                        help="with --relit-gain: the relit frame is a smooth per-cell mix of the gained base and the "
                             "input under its own gain (refiner.RefinerConfig.input_mix): the input's detail where it holds")
    parser.add_argument("--alike-weight", type=float, default=1.0,
                        help="draw the items whose input is within --alike-db of the target (the new light changes "
                             "little: the test split has twice the training share of them) this many times as often")
    parser.add_argument("--alike-db", type=float, default=24.0, help="see --alike-weight (dB; default 24)")
    parser.add_argument("--zero-head", action="store_true",
                        help="with --init: start the corrected clips' correction at zero (from a refiner trained for other clips)")
    parser.add_argument("--slot", choices=tuple(REFINER_SLOTS), default="refiner",
                        help="--model-dir: the config.json entry it goes in (relit_refiner: a second refiner beside the model's)")
    parser.add_argument("--permute-colours", action="store_true",
                        help="augment each training item with a random order of its RGB channels (all its frames alike)")
    parser.add_argument("--val-every-minutes", type=float, default=7.0)
    parser.add_argument("--threads", type=int, default=1)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--refit", action="store_true",
                        help="fit --model's own refiner in --slot again (after its DiT changed): its shape flags from the "
                             "model's config.json and, unless --init says otherwise, its weights as the start")
    parser.add_argument("--device", default="cpu",
                        help="cpu (default), cuda or cuda:N: where the DiT's outputs are made and the refiner trains "
                             "(bf16 autocast where that device computes it faster); the draws stay on the CPU, so a "
                             "run resumes alike on either")
    args = parser.parse_args(argv)
    if args.refit:
        try:
            refit_flags(args)
        except ValueError as error:
            parser.error(str(error))
    for path in [*args.pack, *args.seen, args.val_pack]:
        if not path.is_file():
            parser.error(f"no pack at {path}")
    if not args.alike_weight > 0 or not args.head_lr >= 0 or not args.transport_lr >= 0:
        parser.error("--alike-weight takes a number above 0, --head-lr and --transport-lr one of 0 or more")
    if args.init is not None and not args.init.is_file():
        parser.error(f"no refiner weights at --init {args.init}")
    if not (args.model / DIT_FILE).is_file():
        parser.error(f"--model {args.model} holds no {DIT_FILE}; give a model folder")
    try:
        flag_config(args)
        resolve_device(args.device)
    except ValueError as error:
        parser.error(str(error))
    threads = torch.get_num_threads()
    try:
        best = train(args)
    except ValueError as error:
        parser.error(str(error))
    finally:
        torch.set_num_threads(threads)    # the caller's (a test session's) threads stay as they were
    print(f"best: step {best['step']}, validation {best['val']} (the DiT's frames: {best['start']})")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
