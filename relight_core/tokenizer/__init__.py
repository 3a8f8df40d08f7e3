"""Video tokenizers: pixels [B,3,T,H,W] in [-1,1] <-> latents [B,16,t,h,w] scaled by sigma_data.

Three implementations share the `Tokenizer` protocol:

* `CausalVideoAutoencoder` — the project's small trainable tokenizer (8× space, causal 1/2/4/8× time,
  16 channels), cheap enough for a laptop CPU;
* `PixelTokenizer` — fixed, lossless space-to-depth patches (8× space, no time compression,
  3·8² = 192 channels): the default model's tokenizer, nothing to train;
* `CosmosJITTokenizer` — the released Cosmos CV8x8x8 TorchScript encoder/decoder pair that the
  UniRelight 7B weights were trained with.

Time is causal in both: the first frame is encoded alone (an image is one latent frame) and every
further group of `temporal_factor` frames becomes one latent frame, so `T = 1 + k·temporal_factor`.
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import torch
from safetensors.torch import load_file

from relight_core.errors import InputError
from relight_core.tokenizer.base import (
    SIGMA_DATA,
    SIZE_MULTIPLE,
    Tokenizer,
    check_frames,
    check_size,
    check_video,
    latent_frames,
    pixel_frames,
)
from relight_core.tokenizer.causal_ae import (
    TOKENIZER_PRESETS,
    CausalVideoAutoencoder,
    TokenizerConfig,
    tokenizer_loss,
)
from relight_core.tokenizer.cosmos_jit import CosmosJITTokenizer
from relight_core.tokenizer.pixel import PixelTokenizer

__all__ = [
    "SIGMA_DATA",
    "SIZE_MULTIPLE",
    "TOKENIZER_PRESETS",
    "CausalVideoAutoencoder",
    "CosmosJITTokenizer",
    "PixelTokenizer",
    "Tokenizer",
    "TokenizerConfig",
    "build_tokenizer",
    "check_frames",
    "check_size",
    "check_video",
    "latent_frames",
    "pixel_frames",
    "tokenizer_loss",
]


def _resolve(name: str, weights_dir: Path | None) -> Path:
    """A file named in a spec, relative to weights_dir; InputError naming it when missing."""
    path = Path(name) if weights_dir is None else Path(weights_dir) / name
    if not path.is_file():
        raise InputError(f"Tokenizer file {path} does not exist: check the model folder and its config.")
    return path


def build_tokenizer(
    spec: dict, weights_dir: Path | None = None, device: str | torch.device = "cpu"
) -> Tokenizer:
    """Build a tokenizer from a JSON-able spec; file names are relative to weights_dir.

    `{"type": "causal-ae", "preset": "small", "weights": "tokenizer.safetensors", **config fields}`
    or `{"type": "pixel", "patch": 8}`
    or `{"type": "cosmos-jit", "encoder": "encoder.jit", "decoder": "decoder.jit",
    "mean_std": "mean_std.pt", "image_mean_std": "image_mean_std.pt", "dtype": "bfloat16"}`.
    """
    spec = dict(spec)
    kind = spec.pop("type", None)
    if kind == "causal-ae":
        preset = spec.pop("preset", "small")
        if preset not in TOKENIZER_PRESETS:
            raise InputError(f"Unknown tokenizer preset {preset!r}: use one of {sorted(TOKENIZER_PRESETS)}.")
        weights = spec.pop("weights", None)
        fields = {f.name for f in dataclasses.fields(TokenizerConfig)}
        unknown = sorted(set(spec) - fields)
        if unknown:
            raise InputError(f"Unknown tokenizer config keys {unknown}: use only {sorted(fields)}.")
        if "channels" in spec:
            spec["channels"] = tuple(spec["channels"])
        model = CausalVideoAutoencoder(dataclasses.replace(TOKENIZER_PRESETS[preset], **spec))
        if weights is not None:
            model.load_state_dict(load_file(_resolve(weights, weights_dir)))
        return model.to(device).eval()
    if kind == "pixel":
        unknown = sorted(set(spec) - {"patch", "scale"})
        if unknown:
            raise InputError(f"Unknown pixel tokenizer keys {unknown}: use only patch and scale.")
        return PixelTokenizer(int(spec.get("patch", 8)), float(spec.get("scale", 1.0))).to(device).eval()
    if kind == "cosmos-jit":
        dtype = getattr(torch, spec.get("dtype", "bfloat16"), None)
        if not isinstance(dtype, torch.dtype):
            raise InputError(f"Unknown tokenizer dtype {spec['dtype']!r}: use bfloat16 or float32.")
        optional = {key: _resolve(spec[key], weights_dir) for key in ("mean_std", "image_mean_std") if spec.get(key)}
        return CosmosJITTokenizer(
            _resolve(spec.get("encoder", "encoder.jit"), weights_dir),
            _resolve(spec.get("decoder", "decoder.jit"), weights_dir),
            mean_std_path=optional.get("mean_std"),
            image_mean_std_path=optional.get("image_mean_std"),
            dtype=dtype,
            device=device,
        )
    raise InputError(f"Unknown tokenizer type {kind!r}: use 'causal-ae', 'pixel' or 'cosmos-jit'.")
