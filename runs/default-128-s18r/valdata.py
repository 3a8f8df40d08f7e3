"""The validation items these scripts score: the first 128 seed-5 train scenes (s5/val.npz, both directions),
with the shipped DiT's outputs cached as training.refine caches them (s5/outputs-val.npz)."""
import json
from pathlib import Path

from safetensors.torch import load_file

from relight_core.checkpoint import load_model
from relight_core.refiner import Refiner, RefinerConfig
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
    """The shipped refiner's shape with `weights` (default: the shipped ones), in fp32."""
    config = RefinerConfig.from_dict(json.loads((MODEL / "config.json").read_text())["refiner"])
    model = Refiner(config)
    state = load_file(weights or MODEL / "refiner.safetensors")
    model.load_state_dict({k: v.float() for k, v in state.items()})
    return model.eval()
