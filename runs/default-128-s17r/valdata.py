"""The validation items these scripts score: the 128 held-out scenes of s15/val.npz, both directions, with
the DiT's cached outputs (refine/big/outputs-val.npz) as training.refine builds them for `base`."""
from pathlib import Path

import numpy as np

from relight_core.checkpoint import load_model
from relight_core.training import refine
from relight_core.training.pack import load_packs

CACHE = Path.home() / ".cache/unirelight-studio"


def validation(base: str = "filtered") -> dict:
    spec, _, _ = load_model(Path("models/default"), "cpu")
    pack = load_packs([CACHE / "s15/val.npz"])
    items = [(i, t) for i in range(len(pack["names"])) for t in (0, 1)]
    with np.load(CACHE / "refine/big/outputs-val.npz") as z:
        outputs = {"relit": z["relit"], "albedo": z["albedo"]}
    return refine.item_tensors(pack, items, outputs, spec, base)
