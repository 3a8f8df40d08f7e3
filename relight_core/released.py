"""Turn the released UniRelight files into one of our model folders.

The user downloads two things (we never fetch them): the UniRelight checkpoint (`UniRelight/model.pt`,
a PyTorch file holding the Cosmos GeneralDIT weights under a `net.` prefix) and the
`Cosmos-Tokenize1-CV8x8x8-720p` folder (`encoder.jit`, `decoder.jit`, `mean_std.pt`). The checkpoint
is read with `torch.load(weights_only=True)` — no pickled code runs — and memory-mapped, so a 7B
checkpoint does not need its size in RAM. Its weights are renamed with `released_to_ours` (below),
checked against our architecture, and written as `dit.safetensors` next to a `config.json` whose
tokenizer spec points at the tokenizer folder.
"""

from __future__ import annotations

import dataclasses
import json
import pickle
import re
import zipfile
from pathlib import Path

import torch
from safetensors.torch import save_file

from relight_core.checkpoint import CONFIG_FILE, DIT_FILE, MODEL_PRESETS
from relight_core.dit import DiTConfig, JointDiT
from relight_core.errors import InputError

# Names in a released checkpoint that carry no weights of ours (position tables, loss weights).
IGNORED_SUFFIXES = ("_extra_state", "pos_embedder.seq", "pos_embedder.dim_spatial_range",
                    "pos_embedder.dim_temporal_range")


def _read_checkpoint(path: Path) -> dict[str, torch.Tensor]:
    """The network tensors of a released checkpoint, without unpickling code."""
    if not path.is_file():
        raise InputError(f"No released checkpoint at {path}; pass the path of UniRelight/model.pt.")
    try:
        data = torch.load(path, map_location="cpu", weights_only=True, mmap=True)
    except (pickle.UnpicklingError, RuntimeError, zipfile.BadZipFile, EOFError, ValueError) as exc:
        raise InputError(f"{path} is not a readable PyTorch checkpoint ({str(exc).splitlines()[0]}); "
                         "download it again.") from exc
    for key in ("model", "state_dict", "ema"):
        if isinstance(data, dict) and isinstance(data.get(key), dict):
            data = data[key]
            break
    if not isinstance(data, dict) or not all(isinstance(v, torch.Tensor) for v in data.values()):
        raise InputError(f"{path} does not hold a dictionary of tensors; it is not a UniRelight checkpoint.")
    return data


def import_released(checkpoint: str | Path, tokenizer_dir: str | Path, out: str | Path,
                    dit_config: DiTConfig | None = None) -> Path:
    """Write a model folder for the released weights; returns the folder."""
    checkpoint, tokenizer_dir, out = Path(checkpoint), Path(tokenizer_dir).resolve(), Path(out)
    for name in ("encoder.jit", "decoder.jit"):
        if not (tokenizer_dir / name).is_file():
            raise InputError(f"The tokenizer folder {tokenizer_dir} has no {name}; pass the "
                             "Cosmos-Tokenize1-CV8x8x8-720p folder.")
    spec = MODEL_PRESETS["unirelight-7b"]
    config = dit_config or spec.dit
    state = _read_checkpoint(checkpoint)
    prefix = "net." if any(k.startswith("net.") for k in state) else ""
    converted, unmapped = convert_released_state_dict(
        {k: v for k, v in state.items() if not k.startswith("net_ema.")}, prefix=prefix)
    unmapped = [k for k in unmapped if k.startswith(prefix) and not k.endswith(IGNORED_SUFFIXES)]
    with torch.device("meta"):
        expected = {k: v.shape for k, v in JointDiT(config).state_dict().items()}
    missing = sorted(set(expected) - set(converted))
    wrong = sorted(k for k in expected if k in converted and converted[k].shape != expected[k])
    if missing or wrong or unmapped:
        raise InputError(f"{checkpoint} does not match the UniRelight 7B architecture: {len(missing)} weights "
                         f"missing (e.g. {missing[:2]}), {len(wrong)} with other shapes (e.g. {wrong[:2]}), "
                         f"{len(unmapped)} unknown (e.g. {unmapped[:2]}).")
    out.mkdir(parents=True, exist_ok=True)
    save_file({k: converted[k].contiguous() for k in expected}, out / DIT_FILE)
    tokenizer = {"type": "cosmos-jit", "encoder": str(tokenizer_dir / "encoder.jit"),
                 "decoder": str(tokenizer_dir / "decoder.jit")}
    for key in ("mean_std", "image_mean_std"):  # latent statistics shipped beside the JIT files
        if (tokenizer_dir / f"{key}.pt").is_file():
            tokenizer[key] = str(tokenizer_dir / f"{key}.pt")
    released = dataclasses.replace(spec, dit=config, tokenizer=tokenizer, trained=True,
                                   notes={"source": str(checkpoint.resolve())})
    (out / CONFIG_FILE).write_text(json.dumps(released.to_json(), indent=2))
    return out


#################################################################################
#                Released checkpoint names (Cosmos-Predict1 GeneralDIT)         #
#################################################################################

def released_key_map() -> list[tuple[str, str]]:
    """The rename table: (released GeneralDIT name regex, our name template), `\\1` = block index."""
    table = [
        (r"x_embedder\.proj\.1\.weight", "patch_embed.weight"),
        (r"view_embeddings\.weight", "clip_type_embed.weight"),
        (r"t_embedder\.1\.linear_([12])\.weight", r"t_embedder.linear_\1.weight"),
        (r"affline_norm\.weight", "t_embedder.norm.weight"),
        (r"final_layer\.linear\.weight", "final_layer.linear.weight"),
        (r"final_layer\.adaLN_modulation\.1\.weight", "final_layer.modulation.down.weight"),
        (r"final_layer\.adaLN_modulation\.2\.weight", "final_layer.modulation.up.weight"),
    ]
    # Released blocks are "FA-CA-MLP": sub-layer 0 self-attention, 1 cross-attention, 2 MLP.
    sublayers = {"0": "self_attn", "1": "cross_attn", "2": "mlp"}
    attention = {"to_q.0": "q_proj", "to_q.1": "q_norm", "to_k.0": "k_proj", "to_k.1": "k_norm",
                 "to_v.0": "v_proj", "to_out.0": "out_proj"}
    mlp = {"layer1": "fc1", "layer2": "fc2"}
    block = r"blocks\.block(\d+)\.blocks\."
    for index, ours in sublayers.items():
        table.append((rf"{block}{index}\.adaLN_modulation\.1\.weight", rf"blocks.\1.{ours}_mod.down.weight"))
        table.append((rf"{block}{index}\.adaLN_modulation\.2\.weight", rf"blocks.\1.{ours}_mod.up.weight"))
        parts = mlp if ours == "mlp" else attention
        inner = "block" if ours == "mlp" else r"block\.attn"
        for released, part in parts.items():
            table.append((rf"{block}{index}\.{inner}\.{re.escape(released)}\.weight",
                          rf"blocks.\1.{ours}.{part}.weight"))
    return table


_RELEASED_KEY_MAP = [(re.compile(pattern), target) for pattern, target in released_key_map()]


def released_to_ours(name: str) -> str | None:
    """Our parameter name for a released GeneralDIT name, or None (buffers, extra state)."""
    for pattern, target in _RELEASED_KEY_MAP:
        match = pattern.fullmatch(name)
        if match is not None:
            return match.expand(target)
    return None


def convert_released_state_dict(state_dict: dict[str, torch.Tensor], prefix: str = "net."
                                ) -> tuple[dict[str, torch.Tensor], list[str]]:
    """Rename a released checkpoint's network weights to ours; also returns the keys left unmapped."""
    converted, unmapped = {}, []
    for name, tensor in state_dict.items():
        ours = released_to_ours(name[len(prefix):] if prefix and name.startswith(prefix) else name)
        if ours is None:
            unmapped.append(name)
        else:
            converted[ours] = tensor
    return converted, unmapped
