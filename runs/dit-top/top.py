"""The DiT's top blocks trained on a CPU over a frozen, cached trunk (2026-12-07, third session).

CPU rounds of the whole DiT did not move the GPU-trained one: a CPU thread affords ~2.5 samples a second,
and the GPU round's gain took ~66,000 (docs/TRAINING.md, "A GPU's batch on a CPU"). The shipped model runs
the DiT once, at σ 80 (one step: x0 ≈ input + c_out·F(c_in·x_T); the closing σ 0.002 call moves it by
< 0.01), so only that regime matters. Here the first K blocks are frozen and their output tokens cached once
per item (on one noise draw, as the shipped sampler's seed), and only blocks K.. and the final layer train,
each sample costing the top's share of a forward and backward: many times the samples a CPU can afford.

    cache: PYTHONPATH=. python runs/dit-top/top.py cache OUT --packs P1.npz ... --items N [--val VAL.npz]
    (per item: the trunk's tokens, F, x0, the targets, the mask, and the input frame and target probe that
    through.py's refiners need; packs made with `training.pack --lossless` give what evaluation gives)
    train: PYTHONPATH=. python runs/dit-top/top.py train OUT --minutes M [--lr 1e-4] [--batch 16] [--init DIR]
    (the best EMA by validation is written to OUT/model/, the shipped folder with its DiT's top replaced)

The loss is the protocol's (refine.item_loss: scale-fitted log MSE on the mask) on the relit frame, plus
half of it on the albedo, each decoded from x0 = x0_shipped + c_out·(F_new − F_shipped); `--margin W` adds
W·(that relit loss − the relit loss against the scene under the other light), for which train needs the cache run's
--packs, --items and --seed. Validation scores relit, albedo and the relit margin of the DiT alone; what it found
through the whole pipeline (it does not carry): runs/dit-top/README.md.
"""
from __future__ import annotations

import argparse
import copy
import json
import math
import shutil
import sys
import time
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import save_file

from relight_core.checkpoint import load_model
from relight_core.diffusion import edm_scalings
from relight_core.dit import NUM_CLIPS
from relight_core.precision import resolve_precision
from relight_core.training.fast import make_batch, sample_relight
from relight_core.training.pack import load_packs
from relight_core.training.refine import _hwc, item_loss
from relight_core.evaluation.metrics import protocol_psnr

MODEL = Path("models/default")
SIGMA = 80.0


def log(out: Path, **record) -> None:
    record["time"] = time.strftime("%H:%M:%S")
    line = json.dumps(record)
    print(line, flush=True)
    with open(out / "log.jsonl", "a") as f:
        f.write(line + "\n")


def cache(args) -> None:
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    torch.set_num_threads(args.threads)
    spec, dit, tokenizer = load_model(MODEL)
    autocast = resolve_precision("auto", torch.device("cpu")) == torch.bfloat16
    captured = {}

    def trunk_hook(_, __, output):
        if "tokens" not in captured:
            captured["tokens"] = output.detach().half()

    def net_hook(_, __, output):
        if "f" not in captured:
            captured["f"] = output.detach().float()

    dit.blocks[args.k - 1].register_forward_hook(trunk_hook)
    dit.register_forward_hook(net_hook)

    def run(pack, scenes, targets, name):
        chunk = {"tokens": [], "f": [], "x0": [], "relit_t": [], "albedo_t": [], "mask": [], "input": [], "env": []}
        started = time.time()
        for start in range(0, len(scenes), args.batch):
            s, t = scenes[start:start + args.batch], targets[start:start + args.batch]
            data = make_batch(pack, tokenizer, s, t, torch.zeros(len(s), dtype=torch.bool))
            captured.clear()
            with torch.no_grad():
                x0 = sample_relight(dit, data, 1, autocast=autocast, residual=True)   # seed 0, as dit_outputs
            chunk["tokens"].append(captured["tokens"])
            chunk["f"].append(captured["f"][:, :, 1:].half())                 # relit, albedo clips [B,192,2,h,w]
            chunk["x0"].append(x0[:, :, 1:].half())
            chunk["relit_t"].append(pack["rgb"][s, t])                          # uint8 [B,3,H,W]
            chunk["albedo_t"].append(pack["albedo"][s])
            chunk["mask"].append(pack["mask"][s])
            chunk["input"].append(pack["rgb"][s, 1 - t])                        # what the refiners see too
            chunk["env"].append(torch.as_tensor(pack["env"])[s, t].float())     # the target's camera-frame probe
            done = start + len(s)
            if (done // args.batch) % 20 == 0 or done == len(scenes):
                log(out, event="cache", name=name, done=done, of=len(scenes),
                    seconds=round(time.time() - started, 1))
            if sum(len(x) for x in chunk["tokens"]) >= args.chunk or done == len(scenes):
                part = {k: torch.cat(v) for k, v in chunk.items()}
                index = len(list(out.glob(f"{name}-*.pt")))
                torch.save(part, out / f"{name}-{index:03d}.partial")
                (out / f"{name}-{index:03d}.partial").replace(out / f"{name}-{index:03d}.pt")
                chunk = {k: [] for k in chunk}

    if args.val:
        val = load_packs([Path(args.val)])
        n = len(val["rgb"])
        scenes = torch.arange(n).repeat_interleave(2)
        targets = torch.tensor([0, 1]).repeat(n)
        if not list(out.glob("val-*.pt")):
            run(val, scenes, targets, "val")
    pack = load_packs([Path(p) for p in args.packs])
    n = len(pack["rgb"])
    g = torch.Generator().manual_seed(args.seed)
    order = torch.randperm(n, generator=g)[:args.items]
    targets = torch.randint(0, 2, (n,), generator=g)[order]
    done = sum(torch.load(p, weights_only=True)["mask"].shape[0] for p in out.glob("train-*.pt"))
    run(pack, order[done:], targets[done:], "train")


class Top(torch.nn.Module):
    """Blocks k.. and the final layer of a JointDiT, on cached trunk tokens at σ 80."""

    def __init__(self, dit, k: int):
        super().__init__()
        self.blocks = copy.deepcopy(dit.blocks[k:])
        self.final_layer = copy.deepcopy(dit.final_layer)
        self.dit = dit                                                            # frozen: embeddings, unpatchify
        sigma = torch.tensor([SIGMA])
        _, self.c_out, _, c_noise = edm_scalings(sigma)
        autocast = resolve_precision("auto", torch.device("cpu")) == torch.bfloat16
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):  # as in the DiT's call
            emb, lora = dit.t_embedder(c_noise.flatten().float())
        self.register_buffer("emb", emb.float())
        self.register_buffer("lora", lora.float())
        cos, sin = dit.rope(1, 16, 16, torch.device("cpu"))
        self.rope = (cos, sin)

    def forward(self, tokens: torch.Tensor) -> torch.Tensor:
        b = tokens.shape[0]
        emb, lora = self.emb.expand(b, -1), self.lora.expand(b, -1)
        tokens = tokens.float()
        for block in self.blocks:
            tokens = block(tokens, emb, lora, self.rope)
        out = self.final_layer(tokens, emb, lora)
        return self.dit.unpatchify(out, NUM_CLIPS, 16, 16).float()[:, :, 1:]      # relit, albedo [B,192,2,h,w]


def frames(tokenizer, x0: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """relit, albedo [B,3,H,W] in [-1, 1] from x0 clips [B,192,2,h,w]."""
    relit = tokenizer.decode(x0[:, :, 0:1])[:, :, 0]
    albedo = tokenizer.decode(x0[:, :, 1:2])[:, :, 0]
    return relit.clamp(-1, 1), albedo.clamp(-1, 1)


class Chunks:
    """The cached chunks, memory-mapped (runs side by side share the page cache); `gather` reads rows."""

    def __init__(self, out: Path, name: str):
        self.parts = [torch.load(p, weights_only=True, mmap=True) for p in sorted(out.glob(f"{name}-*.pt"))]
        sizes = [len(p["mask"]) for p in self.parts]
        self.starts = np.cumsum([0] + sizes)

    def __len__(self) -> int:
        return int(self.starts[-1])

    def gather(self, key: str, index) -> torch.Tensor:
        """Rows `index` (a slice or indices) of `key`, stacked."""
        if isinstance(index, slice):
            index = torch.arange(len(self))[index]
        index = torch.as_tensor(index).numpy()
        part = np.searchsorted(self.starts, index, side="right") - 1
        return torch.stack([self.parts[k][key][int(i - self.starts[k])] for k, i in zip(part, index)])


def scores(top, tokenizer, val, autocast, batch=32) -> dict:
    """Protocol PSNR (relit, albedo) of the top's one-step frames on `val`, and the relit margin; batch even."""
    relit_p, albedo_p, other_p = [], [], []
    for start in range(0, len(val), batch):
        part = slice(start, start + batch)
        tokens = val.gather("tokens", part)                                     # gathered outside autocast
        with torch.no_grad(), torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            f = top(tokens)
        x0 = val.gather("x0", part).float() + top.c_out * (f - val.gather("f", part).float())
        relit, albedo = frames(tokenizer, x0)
        masks = val.gather("mask", part).numpy()
        rt, at = _hwc(val.gather("relit_t", part)), _hwc(val.gather("albedo_t", part))
        r, a = (((x.permute(0, 2, 3, 1).numpy() + 1) / 2).astype(np.float32) for x in (relit, albedo))
        relit_p += [protocol_psnr(r[i:i + 1], rt[i:i + 1], masks[i:i + 1]) for i in range(len(masks))]
        albedo_p += [protocol_psnr(a[i:i + 1], at[i:i + 1], masks[i:i + 1]) for i in range(len(masks))]
        # the probe-following margin: val holds both directions of each scene, in turn (item i's other light is i ^ 1)
        other_p += [protocol_psnr(r[i:i + 1], rt[i ^ 1:(i ^ 1) + 1], masks[i:i + 1]) for i in range(len(masks))]
    return {"relit": round(float(np.mean(relit_p)), 4), "albedo": round(float(np.mean(albedo_p)), 4),
            "margin": round(float(np.mean(relit_p) - np.mean(other_p)), 4)}


def train(args) -> None:
    out = Path(args.out)
    torch.set_num_threads(args.threads)
    torch.manual_seed(args.seed)
    spec, dit, tokenizer = load_model(args.init or MODEL)  # --init: a round's OUT/model, to go on from its top
    autocast = resolve_precision("auto", torch.device("cpu")) == torch.bfloat16
    top = Top(dit, args.k)
    for p in top.parameters():
        p.requires_grad_(False)
    params = [p for m in (top.blocks, top.final_layer) for p in m.parameters()]
    for p in params:
        p.requires_grad_(True)
    val = Chunks(out, "val")
    train_set = Chunks(out, "train")
    n = len(train_set)
    other = other_targets(args, train_set) if args.margin else None
    log(out, event="start", init=str(args.init or MODEL), items=n, val_items=len(val), k=args.k, lr=args.lr, batch=args.batch,
        params=sum(p.numel() for p in params), threads=args.threads, margin=args.margin, select_margin=args.select_margin)

    def step_loss(index: torch.Tensor) -> torch.Tensor:
        tokens = train_set.gather("tokens", index)                              # gathered outside autocast
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            f = top(tokens)
        x0 = train_set.gather("x0", index).float() + top.c_out * (f - train_set.gather("f", index).float())
        relit, albedo = frames(tokenizer, x0)
        mask = train_set.gather("mask", index)
        own = item_loss(relit, train_set.gather("relit_t", index).float() / 127.5 - 1, mask)
        loss = own + 0.5 * item_loss(albedo, train_set.gather("albedo_t", index).float() / 127.5 - 1, mask)
        if other is not None:                   # the margin: as near its own light's frame, as far from the other's
            loss = loss + args.margin * (own - item_loss(relit, other[index].float() / 127.5 - 1, mask))
        return loss

    fit(args, out, [{"params": params, "base": args.lr}], n, step_loss,
        lambda: scores(top, tokenizer, val, autocast), lambda: export(top, dit, args.k, out))


def fit(args, out: Path, groups: list[dict], n: int, step_loss, validate, save, log_every: int = 20) -> dict:
    """The training loop of top.py and through.py: AdamW over `groups` (each {"params": [...], "base": its lr}),
    warm-up over args.warmup steps then a cosine to a tenth over args.minutes, gradients clipped to 1, an EMA
    (args.ema) of every parameter; `step_loss(index)` is the loss of training items `index` (args.batch drawn of
    `n`). At the start, every args.val_every minutes and at the end the EMA weights are put in place and
    `validate()` scores them ({"relit", "albedo", "margin"}); the best by relit + ½ albedo + args.select_margin ×
    margin is `save()`d. Logs to OUT/log.jsonl; returns the best."""
    params = [p for group in groups for p in group["params"]]
    ema = [p.detach().clone() for p in params]
    value_of = lambda score: score["relit"] + 0.5 * score["albedo"] + args.select_margin * score["margin"]
    start_score = validate()
    log(out, event="val", step=0, **start_score)
    best = {"score": value_of(start_score), "step": 0, **start_score}
    optimizer = torch.optim.AdamW(groups, lr=args.lr, betas=(0.9, 0.99), weight_decay=0.0)
    started, step, last_val, losses = time.time(), 0, time.time(), []
    budget = args.minutes * 60
    while time.time() - started < budget:
        progress = (time.time() - started) / budget
        factor = min(1.0, (step + 1) / args.warmup) * (0.1 + 0.9 * 0.5 * (1 + math.cos(math.pi * progress)))
        for group in optimizer.param_groups:
            group["lr"] = group["base"] * factor
        loss = step_loss(torch.randint(0, n, (args.batch,)))
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(params, 1.0)
        optimizer.step()
        step += 1
        with torch.no_grad():
            decay = min(args.ema, (1 + step) / (10 + step))
            for e, p in zip(ema, params):
                e.lerp_(p.detach(), 1 - decay)
        losses.append(loss.item())
        if step % log_every == 0:
            log(out, event="loss", step=step, loss=round(float(np.mean(losses)), 4), lr=args.lr * factor,
                seconds=round(time.time() - started, 1))
            losses = []
        if time.time() - last_val > args.val_every * 60 or time.time() - started >= budget:
            last_val = time.time()
            live = [p.detach().clone() for p in params]
            with torch.no_grad():
                for e, p in zip(ema, params):
                    p.copy_(e)
            score = validate()
            value = value_of(score)
            is_best = value > best["score"]
            log(out, event="val", step=step, **score, best=is_best, seconds=round(time.time() - started, 1))
            if is_best:
                best = {"score": value, "step": step, **score}
                save()
            with torch.no_grad():
                for lv, p in zip(live, params):
                    p.copy_(lv)
    log(out, event="end", step=step, best=best)
    return best


def other_targets(args, train_set) -> torch.Tensor:
    """uint8 [N,3,H,W]: each cached training item's scene under its *other* light, from the packs it was cached
    from (--packs, --items and --seed as the cache run: the same draw of scenes and directions, checked)."""
    pack = load_packs([Path(p) for p in args.packs])
    g = torch.Generator().manual_seed(args.seed)
    order = torch.randperm(len(pack["rgb"]), generator=g)[:args.items]
    targets = torch.randint(0, 2, (len(pack["rgb"]),), generator=g)[order]
    probe = torch.tensor([0, len(order) // 2, len(order) - 1])
    if len(order) != len(train_set) or not torch.equal(pack["rgb"][order[probe], targets[probe]],
                                                       train_set.gather("relit_t", probe)):
        raise ValueError("--packs/--items/--seed do not give the draw the cache was made with")
    return pack["rgb"][order, 1 - targets].contiguous()


def export(top, dit, k: int, out: Path) -> None:
    """OUT/model: the shipped folder with the DiT's blocks k.. and final layer from `top` (bf16, as shipped)."""
    state = {name: t.detach().clone() for name, t in dit.state_dict().items()}
    for i, block in enumerate(top.blocks):
        for name, t in block.state_dict().items():
            state[f"blocks.{k + i}.{name}"] = t.detach().clone()
    for name, t in top.final_layer.state_dict().items():
        state[f"final_layer.{name}"] = t.detach().clone()
    folder = out / "model"
    if folder.exists():
        shutil.rmtree(folder)
    shutil.copytree(MODEL, folder)
    save_file({n: t.to(torch.bfloat16).contiguous() for n, t in state.items()}, str(folder / "dit.safetensors"))


def main(argv=None) -> int:
    parser = argparse.ArgumentParser()
    parser.add_argument("mode", choices=["cache", "train"])
    parser.add_argument("out")
    parser.add_argument("--packs", nargs="*", default=[])
    parser.add_argument("--val")
    parser.add_argument("--items", type=int, default=4000)
    parser.add_argument("--k", type=int, default=6)
    parser.add_argument("--batch", type=int, default=16)
    parser.add_argument("--chunk", type=int, default=512)
    parser.add_argument("--threads", type=int, default=2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--minutes", type=float, default=30)
    parser.add_argument("--lr", type=float, default=1e-4)
    parser.add_argument("--warmup", type=int, default=30)
    parser.add_argument("--ema", type=float, default=0.995)
    parser.add_argument("--val-every", type=float, default=5)
    parser.add_argument("--margin", type=float, default=0.0,
                        help="train: weight of the margin term (own-light loss minus other-light loss; needs --packs)")
    parser.add_argument("--select-margin", type=float, default=0.0, help="train: the margin's weight in the choice")
    parser.add_argument("--init", help="a model folder whose DiT top to start from (default: the shipped one)")
    args = parser.parse_args(argv)
    (cache if args.mode == "cache" else train)(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
