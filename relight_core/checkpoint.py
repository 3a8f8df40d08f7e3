"""Model directories: `config.json` + `*.safetensors`, named presets, save/load round trips.

A model directory holds everything the `Relighter` needs:

    config.json            ModelSpec (DiT config, tokenizer spec, chunking and sampling defaults)
    dit.safetensors        JointDiT state dict
    tokenizer.safetensors  trainable tokenizer state dict (absent for the Cosmos JIT tokenizer,
                           whose TorchScript files the tokenizer spec names instead)

`load_model("tiny")` builds a preset with random weights (tests, benchmarks); `load_model(DIR)`
loads a directory; `load_model("default")` loads the small model shipped in `models/default`.
"""

from __future__ import annotations

import dataclasses
import json
from dataclasses import dataclass, field
from pathlib import Path

import torch
from safetensors.torch import load_file, save_file

from relight_core.arguments import MAX_ENSEMBLE, SHIFT_AVERAGES
from relight_core.dit import DIT_PRESETS, DiTConfig, JointDiT
from relight_core.errors import InputError
from relight_core.precision import check_precision
from relight_core.refiner import CONFIG_KEYS as REFINER_CONFIG_KEYS, REFINER_SLOTS, Refiner, RefinerConfig
from relight_core.temporal import check_settings as check_temporal
from relight_core.tokenizer import build_tokenizer

REPO_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_MODEL_DIR = REPO_ROOT / "models" / "default"
CONFIG_FILE = "config.json"
DIT_FILE = "dit.safetensors"
TOKENIZER_FILE = "tokenizer.safetensors"


@dataclass(frozen=True)
class ModelSpec:
    """Everything about a model except its weights."""

    name: str
    dit: DiTConfig
    tokenizer: dict                      # spec for tokenizer.build_tokenizer
    chunk_frames: int = 57               # frames per chunk, 1 + k·temporal_factor
    overlap_frames: int = 9              # frames shared by consecutive chunks, 1 + j·temporal_factor
    size: int = 848                      # default working resolution (long side, pixels)
    steps: int = 35                      # default sampling steps
    sampler: str = "res2ab"              # default sampler
    final_denoise: bool = True           # the clean-up network call at σ_min after the last step (released
                                         # inference); False: the schedule ends at 0 (diffusion.sampling_sigmas)
    precision: str = "auto"              # compute precision: auto | fp32 | bf16 | fp16 (precision.py)
    trained: bool = True                 # False for a preset with random weights
    lighting_size: int | None = None     # probes seen through a size² panorama (lighting.lowpass_panorama)
    residual: bool = False               # relit/albedo diffused as offsets from the input (ConditionedDenoiser)
    residual_gain: tuple[float, float] = (1.0, 1.0)  # (relit, albedo) offset scale, fitted by training.calibrate
    offset_filter: tuple[int, int] = (0, 0)  # (relit, albedo) guided-filter radius (px at `size`) of a
                                             # residual model's offset, 0 = off (upsample.smooth_offset)
    ensemble: int = 1                    # samples averaged into each result; every second one is run on the
                                         # mirror image under the mirrored light (Relighter, MAX_ENSEMBLE)
    shift_average: int = 1               # copies of each sample run on the frames shifted by half a DiT token
                                         # ((0,0), (h,h), (h,0), (0,h)) and shifted back before the mean: the
                                         # token grid's seams average out (Relighter._members; 1, 2 or 4)
    temporal_filter: tuple[int, float, float] = (0, 0.05, 0.3)  # (radius in frames, input colour scale, light
                                         # scale) of the input-guided filter along time on a video's results;
                                         # radius 0 = off (temporal.py)
    refiner: dict | None = None          # the detail refiner's shape (refiner.RefinerConfig) when the folder
                                         # holds refiner.safetensors; None = no refiner
    relit_refiner: dict | None = None    # a second one (relit_refiner.safetensors), e.g. one that sees the
                                         # light for the relit frames; each corrects its clips
    notes: dict = field(default_factory=dict)

    def to_json(self) -> dict:
        """A JSON-able dict; `from_json` inverts it."""
        out = dataclasses.asdict(self)
        out["dit"] = dataclasses.asdict(self.dit)
        return out

    @classmethod
    def from_json(cls, data: dict) -> "ModelSpec":
        """Parse a config.json dict, ignoring keys this version does not know."""
        known = {f.name for f in dataclasses.fields(cls)}
        kwargs = {k: v for k, v in data.items() if k in known}
        if "precision" not in data and "autocast_bf16" in data:
            # Older folders: autocast on meant "the fast precision" (the hardware decides), off meant fp32.
            kwargs["precision"] = "auto" if data["autocast_bf16"] else "fp32"
        check_precision(kwargs.get("precision", "auto"))
        dit_fields = {f.name for f in dataclasses.fields(DiTConfig)}
        kwargs["dit"] = DiTConfig(**{k: _tuples(v) for k, v in data["dit"].items() if k in dit_fields})
        if "residual_gain" in kwargs:
            kwargs["residual_gain"] = tuple(float(g) for g in kwargs["residual_gain"])
        if "offset_filter" in kwargs:
            radii = kwargs["offset_filter"]
            if not isinstance(radii, (list, tuple)) or len(radii) != 2 or not all(
                    isinstance(r, int) and not isinstance(r, bool) and 0 <= r <= 1024 for r in radii):
                raise InputError(f"The model's config.json has offset_filter {radii!r}; it takes two whole numbers "
                                 "of pixels from 0 to 1024 (relit, albedo), or leave it out.")
            kwargs["offset_filter"] = tuple(radii)
        if "ensemble" in kwargs:
            count = kwargs["ensemble"]
            if not isinstance(count, int) or isinstance(count, bool) or not 1 <= count <= MAX_ENSEMBLE:
                raise InputError(f"The model's config.json has ensemble {count!r}; it takes a whole number of "
                                 f"samples from 1 to {MAX_ENSEMBLE}, or leave it out.")
        copies = kwargs.get("shift_average", 1)
        if not isinstance(copies, int) or isinstance(copies, bool) or copies not in SHIFT_AVERAGES:
            raise InputError(f"The model's config.json has shift_average {copies!r}; it takes "
                             f"{', '.join(map(str, SHIFT_AVERAGES))} (copies at half-token shifts), or leave it out.")
        if "temporal_filter" in kwargs:
            kwargs["temporal_filter"] = check_temporal(kwargs["temporal_filter"])
        for slot in REFINER_SLOTS:
            if kwargs.get(slot) is not None:
                try:
                    kwargs[slot] = RefinerConfig.from_dict(kwargs[slot]).to_dict()
                except (ValueError, TypeError):
                    raise InputError(f"The model's config.json has {slot} {kwargs[slot]!r}; it takes "
                                     f"{REFINER_CONFIG_KEYS}, or leave it out.") from None
        return cls(**kwargs)


def _tuples(value):
    """JSON turns tuples into lists; frozen configs want tuples back."""
    return tuple(value) if isinstance(value, list) else value


MODEL_PRESETS: dict[str, ModelSpec] = {
    "tiny": ModelSpec(
        name="tiny", dit=DIT_PRESETS["tiny"], tokenizer={"type": "causal-ae", "preset": "tiny"},
        chunk_frames=17, overlap_frames=9, size=64, steps=4, trained=False,
    ),
    "small": ModelSpec(
        name="small", dit=DIT_PRESETS["small"], tokenizer={"type": "causal-ae", "preset": "small"},
        chunk_frames=17, overlap_frames=9, size=256, steps=20, trained=False,
    ),
    "unirelight-7b": ModelSpec(
        name="unirelight-7b", dit=DIT_PRESETS["unirelight-7b"],
        tokenizer={"type": "cosmos-jit", "encoder": "encoder.jit", "decoder": "decoder.jit"},
        chunk_frames=57, overlap_frames=9, size=848, steps=35, trained=False,
    ),
}


def has_tokenizer_weights(spec: ModelSpec) -> bool:
    """Whether the model folder holds tokenizer.safetensors (not for the Cosmos JIT files, nor for
    the fixed pixel tokenizer, which has no weights)."""
    return spec.tokenizer.get("type") not in ("cosmos-jit", "pixel")


def save_model(directory: str | Path, spec: ModelSpec, dit: JointDiT, tokenizer) -> Path:
    """Write config.json and the safetensors weights of a model into `directory`."""
    directory = Path(directory)
    directory.mkdir(parents=True, exist_ok=True)
    save_file({k: v.contiguous() for k, v in dit.state_dict().items()}, directory / DIT_FILE)
    if isinstance(tokenizer, torch.nn.Module) and has_tokenizer_weights(spec):
        state = {k: v.contiguous() for k, v in tokenizer.state_dict().items()}
        save_file(state, directory / TOKENIZER_FILE)
    (directory / CONFIG_FILE).write_text(json.dumps(spec.to_json(), indent=2))
    return directory


def resolve_model(model: str | Path) -> tuple[ModelSpec, Path | None]:
    """Turn "default", a preset name or a directory into (spec, weights directory or None)."""
    if str(model) == "default":
        if (DEFAULT_MODEL_DIR / CONFIG_FILE).is_file():
            return _read_spec(DEFAULT_MODEL_DIR), DEFAULT_MODEL_DIR
        return MODEL_PRESETS["tiny"], None
    if str(model) in MODEL_PRESETS:
        return MODEL_PRESETS[str(model)], None
    directory = Path(model).expanduser()
    if not directory.is_dir():
        names = ", ".join(["default", *MODEL_PRESETS])
        raise InputError(f"Model '{model}' is neither a model directory nor a preset ({names}); "
                         "pass a folder holding config.json and *.safetensors.")
    return _read_spec(directory), directory


def _read_spec(directory: Path) -> ModelSpec:
    path = directory / CONFIG_FILE
    if not path.is_file():
        raise InputError(f"The model folder {directory} has no {CONFIG_FILE}; "
                         "point to a folder written by save_model or the convert command.")
    try:
        return ModelSpec.from_json(json.loads(path.read_text()))
    except (ValueError, KeyError, TypeError) as exc:
        raise InputError(f"{path} is not a valid model config ({exc}); re-export the model.") from exc


def load_model(model: str | Path = "default", device: str | torch.device = "cpu",
               dtype: torch.dtype = torch.float32):
    """Build (spec, dit, tokenizer) from a preset name or a model directory; eval mode.

    The DiT's weights come out in `dtype` whatever dtype they are stored in (the compute precision is
    the caller's choice, see precision.py); the tokenizer's come out in fp32.
    """
    spec, directory = resolve_model(model)
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(0)  # a preset's random weights are the same in every process
        tokenizer = build_tokenizer(spec.tokenizer, directory, device)  # the Cosmos JIT loads onto the device
        if directory is None:
            dit = JointDiT(spec.dit)
        else:
            # Weights come from disk: build on the meta device so a 7B model is never
            # materialised twice (random init, then the loaded copy).
            with torch.device("meta"):
                dit = JointDiT(spec.dit)
            _load_state(dit, directory / DIT_FILE, device, dtype)
    if directory is not None and has_tokenizer_weights(spec):
        _load_state(tokenizer, directory / TOKENIZER_FILE, device)
    dit.to(device, dtype).eval().requires_grad_(False)
    if isinstance(tokenizer, torch.nn.Module):
        tokenizer.to(device).eval().requires_grad_(False)
    return spec, dit, tokenizer


def load_refiner(spec: ModelSpec, directory: Path | None, device: str | torch.device = "cpu",
                 slot: str = "refiner") -> Refiner | None:
    """A detail refiner (refiner.py) of a model folder (`resolve_model`'s spec and directory) in fp32,
    eval mode — `slot` "refiner" or "relit_refiner" (`REFINER_SLOTS`) — or None when its config names none."""
    config = getattr(spec, slot)
    if config is None or directory is None:
        return None
    refiner = Refiner(RefinerConfig.from_dict(config))
    _load_state(refiner, directory / REFINER_SLOTS[slot], device, torch.float32)
    return refiner.to(device).eval().requires_grad_(False)


def _load_state(module: torch.nn.Module, path: Path, device: str | torch.device = "cpu",
                dtype: torch.dtype | None = None) -> None:
    """Load a safetensors file into `module`, failing with one sentence on any mismatch.

    Floating-point tensors are cast to `dtype` (default: the dtype the module's own tensors have), so
    a file stored in bf16 never leaves bf16 weights in an fp32 model (`assign=True` would keep them).
    """
    if not path.is_file():
        raise InputError(f"The model folder is missing {path.name} (expected at {path}); "
                         "copy the complete model folder.")
    try:
        state = load_file(str(path), device=str(device))
    except Exception as exc:  # safetensors raises its own error types for corrupt headers
        raise InputError(f"{path} is not a readable safetensors file ({exc}); re-download it.") from exc
    expected = module.state_dict()
    missing = sorted(set(expected) - set(state))
    unexpected = sorted(set(state) - set(expected))
    wrong = [k for k in expected if k in state and state[k].shape != expected[k].shape]
    if missing or unexpected or wrong:
        detail = (f"{len(missing)} missing (e.g. {missing[:2]}), {len(unexpected)} unexpected "
                  f"(e.g. {unexpected[:2]}), {len(wrong)} with the wrong shape (e.g. "
                  f"{[(k, tuple(state[k].shape), tuple(expected[k].shape)) for k in wrong[:2]]})")
        raise InputError(f"The weights in {path} do not match the model in config.json: {detail}.")
    for key, value in state.items():
        if value.is_floating_point():
            target = dtype if dtype is not None else expected[key].dtype
            if value.dtype != target:
                state[key] = value.to(target)
    module.load_state_dict(state, assign=True)
