"""Does a relit refiner that sees the target light help on probes it never trained on?

An experiment (2026-12-05, CPU only): the DiT's one-step relit frames after the offset filter, corrected
by a refiner (relight_core/refiner.py) trained on seed-5 scenes (refine/ft5a's cached DiT outputs) with
two training probes held out entirely (every scene that uses either is out of training); validation on
the held-out scenes' items whose *target* is a held-out probe (new light, as on the test split) and on
val5 (training-like probes). Two arms: the refiner as it is (no light), and the same with the target
probe fed through FiLM (a per-channel scale and shift of every decoder level from an MLP on the
camera-frame probe area-averaged to 8×8, its mean set to 1, log). Both start from the shipped refiner's
weights with the relit head set to zero (= the filtered frames), clips relit.

    python runs/relit-lighting/exp.py prep
    python runs/relit-lighting/exp.py train --arm light --minutes 40 --out $C/relitexp/light
"""
from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np
import torch
from safetensors.torch import load_file

from relight_core.checkpoint import load_model
from relight_core.evaluation.metrics import protocol_psnr
from relight_core.precision import resolve_precision
from relight_core.refiner import Refiner, RefinerConfig, light_features
from relight_core.training.pack import load_packs
from relight_core.training.refine import _hwc, _signed, item_loss, item_tensors, model_inputs, permute_colours

C = Path.home() / ".cache/unirelight-studio"
OUT = C / "relitexp"
HELD = ("file:courtyard", "file:sunrise")
MODEL = Path("models/default")


def probes_of(name: str) -> list[str]:
    return json.loads((C / "data5/train" / name / "meta.json").read_text())["probes"]


def prep() -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    spec, _, _ = load_model(MODEL, "cpu")
    for tag, pack_path, outputs_path in (("train", C / "train-s5.npz", C / "refine/ft5a/outputs-train.npz"),
                                         ("val5", C / "s5/val.npz", C / "s5/outputs-val.npz")):
        pack = load_packs([pack_path])
        names = [str(n) for n in pack["names"]]
        with np.load(outputs_path) as z:
            index = {n: i for i, n in enumerate(names)}
            items = [(index[str(n)], int(t), 0) for n, t in zip(z["names"], z["targets"])]
            outputs = {"relit": z["relit"], "albedo": z["albedo"]}
        started = time.time()
        data = item_tensors(pack, items, outputs, spec, "filtered")
        scenes = torch.tensor([s for s, _, _ in items])
        targets = torch.tensor([t for _, t, _ in items])
        data["env"] = torch.as_tensor(pack["env"])[scenes, targets].float().contiguous()
        probe = [probes_of(names[s]) for s, _, _ in items]
        data["target_probe"] = [p[t] for p, (_, t, _) in zip(probe, items)]
        data["scene_probes"] = probe
        torch.save(data, OUT / f"{tag}.pt")
        print(tag, len(items), f"{time.time() - started:.0f} s", flush=True)


def prep_test() -> None:
    """The test split's 80 items (40 scenes, both directions) packed the same way, for paired scores."""
    from relight_core.training.refine import cached_outputs
    spec, _, _ = load_model(MODEL, "cpu")
    pack = load_packs([C / "test.npz"])
    items = [(s, t, 0) for s in range(len(pack["names"])) for t in (0, 1)]
    outputs = cached_outputs(OUT / "outputs-test.npz", MODEL, pack, items)
    data = item_tensors(pack, items, outputs, spec, "filtered")
    scenes = torch.tensor([s for s, _, _ in items])
    targets = torch.tensor([t for _, t, _ in items])
    data["env"] = torch.as_tensor(pack["env"])[scenes, targets].float().contiguous()
    torch.save(data, OUT / "test.pt")


@torch.no_grad()
def score_test(args) -> None:
    """Per-item relit PSNR and margin on the packed test split for the filtered frames and each run's best
    EMA (`--out` dirs), paired against the filtered frames."""
    torch.set_num_threads(args.threads)
    data = torch.load(OUT / "test.pt", weights_only=True)
    target, source, mask = _hwc(data["target"]), _hwc(data["input"]), data["mask"].numpy()
    autocast = resolve_precision("auto", torch.device("cpu")) == torch.bfloat16

    def per_item(relit):
        own = np.array([protocol_psnr(relit[i], target[i], mask[i]) for i in range(len(mask))])
        other = np.array([protocol_psnr(relit[i], source[i], mask[i]) for i in range(len(mask))])
        return own, own - other

    base_own, base_margin = per_item(_hwc(data["f_relit"]))
    print(f"filtered: relit {base_own.mean():.3f} margin {base_margin.mean():+.3f}")
    for run in args.runs:
        model = make_refiner("light" if "light" in Path(run).name else "plain")
        model.load_state_dict(torch.load(Path(run) / "best.pt", weights_only=True))
        model.eval()
        x, r, _, _ = model_inputs(data, slice(None), "filtered")
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            d = correction(model, x.contiguous(memory_format=torch.channels_last), data["env"]).float()
        own, margin = per_item((((r + d[:, :3]).clamp(-1, 1) + 1) / 2).permute(0, 2, 3, 1).numpy())
        diff = own - base_own
        print(f"{run}: relit {own.mean():.3f} margin {margin.mean():+.3f}; paired relit {diff.mean():+.3f} ± "
              f"{diff.std(ddof=1) / np.sqrt(len(diff)):.3f}, margin {margin.mean() - base_margin.mean():+.3f}")


def make_refiner(arm: str) -> Refiner:
    """The experiment's refiner: the 5-level relit refiner, flip-averaged, seeing the light in the light arm
    (relight_core/refiner.py's FiLM, which this experiment first wrote and then moved there)."""
    return Refiner(RefinerConfig(widths=(24, 48, 96, 128, 256), blocks=1, base="filtered", clips=("relit",),
                                 flip_average=True, lighting=arm == "light"))


def correction(model: Refiner, x: torch.Tensor, light_env: torch.Tensor) -> torch.Tensor:
    """The flip-averaged correction; the mirrored pass sees the mirrored light (panorama u → 1 − u)."""
    return model.correction(x, light_env if model.config.lighting else None)


def subset(data: dict, keep: list[int]) -> dict:
    idx = torch.tensor(keep)
    return {k: (v[idx] if torch.is_tensor(v) else [v[i] for i in keep]) for k, v in data.items()}


@torch.no_grad()
def validate(model, data, autocast) -> dict:
    relit = []
    for start in range(0, len(data["input"]), 32):
        index = slice(start, start + 32)
        x, r, _, _ = model_inputs(data, index, "filtered")
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            d = correction(model, x.contiguous(memory_format=torch.channels_last), data["env"][index]).float()
        relit.append(((r + d[:, :3]).clamp(-1, 1) + 1) / 2)
    relit = torch.cat(relit).permute(0, 2, 3, 1).numpy()
    target, source, mask = _hwc(data["target"]), _hwc(data["input"]), data["mask"].numpy()
    own = [protocol_psnr(relit[i], target[i], mask[i]) for i in range(len(mask))]
    other = [protocol_psnr(relit[i], source[i], mask[i]) for i in range(len(mask))]
    return {"relit": round(float(np.mean(own)), 3), "margin": round(float(np.mean(own) - np.mean(other)), 3)}


def train(args) -> None:
    torch.manual_seed(args.seed)
    torch.set_num_threads(args.threads)
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    data = torch.load(OUT / "train.pt", weights_only=True)
    val5 = torch.load(OUT / "val5.pt", weights_only=True)
    held = [i for i, p in enumerate(data["scene_probes"]) if set(p) & set(HELD)]
    train_idx = [i for i, p in enumerate(data["scene_probes"]) if not set(p) & set(HELD)]
    val_new = [i for i in held if data["target_probe"][i] in HELD]
    rng = np.random.default_rng(0)
    val_new = sorted(rng.choice(val_new, size=min(384, len(val_new)), replace=False).tolist())
    vnew, train_data = subset(data, val_new), subset(data, train_idx)
    del data
    print(f"train items {len(train_idx)}, held-out-probe val {len(val_new)}, val5 {len(val5['input'])}", flush=True)
    model = make_refiner(args.arm)
    state = load_file(str(MODEL / "refiner.safetensors"))
    state = {k: v.float() for k, v in state.items()}
    state["head.weight"][:3] = 0
    state["head.bias"][:3] = 0
    missing, unexpected = model.load_state_dict(state, strict=False)
    assert not unexpected and all(k.startswith("film.") for k in missing), (missing, unexpected)
    model = model.to(memory_format=torch.channels_last)
    autocast = resolve_precision("auto", torch.device("cpu")) == torch.bfloat16
    import copy
    ema = copy.deepcopy(model).eval().requires_grad_(False)
    opt = torch.optim.AdamW(model.parameters(), lr=args.lr, weight_decay=0.0)
    g = torch.Generator().manual_seed(args.seed)
    log = open(out / "log.jsonl", "a")
    s0 = {"new": validate(ema, vnew, autocast), "val5": validate(ema, val5, autocast)}
    print("step 0", s0, flush=True)
    log.write(json.dumps({"step": 0, **s0}) + "\n")
    log.flush()
    count, step, started, last = len(train_data["input"]), 0, time.time(), time.time()
    best = -1e9
    while time.time() - started < args.minutes * 60:
        index = torch.randint(0, count, (args.batch,), generator=g)
        flip = torch.rand(args.batch, generator=g) < 0.5
        x, r, a, get = model_inputs(train_data, index, "filtered", flip)
        env = train_data["env"][index]
        env = torch.where(flip.view(-1, 1, 1, 1), env.flip(2), env)
        target = _signed(get("target"))
        if args.permute:
            order = torch.argsort(torch.rand(args.batch, 3, generator=g), dim=1)
            x, r, target = (permute_colours(t, order) for t in (x, r, target))
            env = env.gather(3, order.view(-1, 1, 1, 3).expand_as(env))
        for group in opt.param_groups:
            group["lr"] = args.lr * min(1.0, (step + 1) / 100)
        with torch.autocast("cpu", dtype=torch.bfloat16, enabled=autocast):
            xc = x.contiguous(memory_format=torch.channels_last)
            d = model(xc, light_features(env) if model.config.lighting else None).float()
        loss = item_loss(r + d[:, :3], target, get("mask"))
        opt.zero_grad(set_to_none=True)
        loss.backward()
        torch.nn.utils.clip_grad_norm_(model.parameters(), 1.0)
        opt.step()
        with torch.no_grad():
            for e, p in zip(ema.parameters(), model.parameters()):
                e.lerp_(p, 1 - args.ema)
        step += 1
        if step % 50 == 0:
            print(f"step {step} loss {loss.item():.4f} {(time.time() - started) / 60:.1f} min", flush=True)
        if time.time() - last > args.val_every * 60 or time.time() - started >= args.minutes * 60:
            last = time.time()
            s = {"new": validate(ema, vnew, autocast), "val5": validate(ema, val5, autocast)}
            rec = {"step": step, "minutes": round((time.time() - started) / 60, 1), **s}
            print(rec, flush=True)
            log.write(json.dumps(rec) + "\n")
            log.flush()
            if s["new"]["relit"] > best:
                best = s["new"]["relit"]
                torch.save(ema.state_dict(), out / "best.pt")
    print("done", flush=True)


if __name__ == "__main__":
    p = argparse.ArgumentParser()
    p.add_argument("what", choices=("prep", "prep-test", "train", "score-test"))
    p.add_argument("--runs", nargs="*", default=[])
    p.add_argument("--arm", choices=("plain", "light"), default="light")
    p.add_argument("--out", default=str(OUT / "run"))
    p.add_argument("--minutes", type=float, default=40)
    p.add_argument("--lr", type=float, default=5e-4)
    p.add_argument("--ema", type=float, default=0.998)
    p.add_argument("--batch", type=int, default=16)
    p.add_argument("--threads", type=int, default=1)
    p.add_argument("--val-every", type=float, default=6)
    p.add_argument("--permute", action="store_true")
    p.add_argument("--seed", type=int, default=0)
    a = p.parse_args()
    if a.what == "train":
        train(a)
    elif a.what == "score-test":
        score_test(a)
    else:
        {"prep": prep, "prep-test": prep_test}[a.what]()
    sys.exit(0)
