"""The validation items these scripts score: the first 128 seed-5 train scenes (s5/val.npz, both directions),
with the shipped DiT's outputs cached as training.refine caches them (s5/outputs-val.npz)."""
from pathlib import Path

import torch
from safetensors.torch import load_file

from relight_core.checkpoint import load_model, load_refiner, resolve_model
from relight_core.precision import resolve_precision
from relight_core.refiner import Refiner
from relight_core.training import refine
from relight_core.training.pack import load_packs

CACHE = Path.home() / ".cache/unirelight-studio"
MODEL = Path("models/default")


def validation(base: str = "filtered") -> dict:
    spec, _, _ = load_model(MODEL, "cpu")
    pack = load_packs([CACHE / "s5/val.npz"])
    items = [(i, t) for i in range(len(pack["names"])) for t in (0, 1)]
    outputs = refine.cached_outputs(CACHE / "s5/outputs-val.npz", MODEL, pack, items)
    return refine.item_tensors(pack, items, outputs, spec, base)


def refiner(weights: Path | None = None) -> Refiner:
    """The shipped refiner (fp32, as the Relighter loads it), with `weights` instead of its own if given."""
    model = load_refiner(*resolve_model(MODEL))
    if weights is not None:
        model.load_state_dict({k: v.float() for k, v in load_file(weights).items()})
    return model


def bf16() -> bool:
    """Whether to score under bf16 autocast: what `auto` picks on this CPU (never on an AVX2-only one)."""
    return resolve_precision("auto", "cpu") == torch.bfloat16
