"""Measuring a model on a rendered dataset: the items, the model runs and every reference number.

Everything goes through the public `Relighter` API and the dataset format (`RelightDataset`,
docs/DATA.md), so any model folder or preset can be measured. An item is one direction of a
synthetic scene (input under probe A → target under probe B); the lighting handed to the model is
exactly the dataset's camera-frame panorama of the target (`env<B>/`), passed as
`RelightRequest.camera_probe`. Items are measured at the model's size, or at another size
(`evaluate --size`): then, as in the CLI and the studio, the model runs at its size and its results
come back by guided ratio upsampling — how a model trained at a small size is compared with others.
Next to the model's numbers, each item set gets:

* floor — the input returned unchanged, as relit and as albedo;
* ceiling — the model's tokenizer encode→decode of the ground-truth target and albedo (at the
  model's size, brought to the measured size the way results are when the two differ);
* probe-following margin — with the same input relit under both probes,
  ½[(P(r_B, t_B) − P(r_B, t_A)) + (P(r_A, t_A) − P(r_A, t_B))], P the protocol PSNR, t_X the scene
  under probe X (t_A is the input itself): exactly 0 for a model whose output ignores the probe;
* the denoiser's error at each σ of the sampling schedule: the clean [input | relit | albedo]
  latents noised to σ and denoised once through the very conditioning `Relighter` builds, with and
  without the lighting, decoded and scored.
"""

from __future__ import annotations

import time
from contextlib import contextmanager
from dataclasses import dataclass, replace

import numpy as np
import torch

from relight_core import media
from relight_core.chunking import pad_to_valid
from relight_core.data.dataset import RelightDataset, read_stream
from relight_core.diffusion import SAMPLERS
from relight_core.errors import InputError
from relight_core.evaluation.metrics import albedo_metrics, protocol_metrics
from relight_core.pipeline import Relighter, RelightRequest
from relight_core.precision import autocast


@dataclass(frozen=True)
class EvalItem:
    """One directed pair of a synthetic scene, frames in [0, 1]."""

    name: str                # "<sample> <input light>→<target light>"
    input: np.ndarray        # [T,H,W,3] the scene under the input's probe
    target: np.ndarray       # [T,H,W,3] the same scene under the target's probe
    albedo: np.ndarray       # [T,H,W,3]
    mask: np.ndarray         # [T,H,W] 1 = geometry
    probe: np.ndarray        # [T,H,W,3] linear camera-frame panoramas of the target's probe (env<target>/)
    other_probe: np.ndarray  # [T,H,W,3] the input's own probe (env<input>/)


def _pixels(tensor: torch.Tensor) -> np.ndarray:
    """[3,T,H,W] in [−1, 1] → [T,H,W,3] in [0, 1]."""
    return ((tensor.permute(1, 2, 3, 0).numpy() + 1) / 2).astype(np.float32)


def load_items(root, split: str, count: int | None = None, spread: bool = False, skip: int = 0) -> list[EvalItem]:
    """The first `count` relightable items of a split (all when None), or `count` evenly spread;
    `skip` leaves out the split's first items (those `evaluate --limit skip` reports on)."""
    dataset = RelightDataset(root, split)
    usable = [i for i, item in enumerate(dataset.items) if item.input_light is not None][skip:]
    if not usable:
        after = f" after its first {skip} items" if skip else ""
        raise InputError(f"The {split} split of {root} has no scene rendered under two probes{after}; "
                         "evaluate on data written by render-data.")
    if count is not None and count < len(usable):
        usable = [usable[round(k * (len(usable) - 1) / max(count - 1, 1))] for k in range(count)] if spread \
            else usable[:count]
    items = []
    for index in usable:
        item = dataset.items[index]
        sample = dataset[index]
        if sample["path"] != str(item.sample_dir) or not bool(sample["has_lighting"]):
            continue  # unreadable (reported by the dataset) or without probes
        frames = list(range(sample["relit"].shape[1]))
        items.append(EvalItem(
            name=f"{item.sample_dir.name} {item.input_light}→{item.target_light}",
            input=_pixels(sample["input"]), target=_pixels(sample["relit"]), albedo=_pixels(sample["albedo"]),
            mask=sample["mask"][0].numpy(),
            probe=read_stream(item.sample_dir, f"env{item.target_light}", frames),
            other_probe=read_stream(item.sample_dir, f"env{item.input_light}", frames)))
    return items


def resized(item: EvalItem, size: int, multiple: int) -> EvalItem:
    """The item's frames and mask with the long side at `size` (sides multiples of `multiple`).

    The probes keep their size: `Relighter` re-grids a camera-frame panorama to the frames' size.
    """
    def frames(x: np.ndarray) -> np.ndarray:
        return media.resize_frames(x, size, multiple=multiple)

    mask = frames(np.repeat(item.mask[..., None], 3, axis=-1))[..., 0] > 0.5
    return replace(item, input=frames(item.input), target=frames(item.target), albedo=frames(item.albedo),
                   mask=mask.astype(np.float32))


# ---------------------------------------------------------------------------------------------
# Model runs
# ---------------------------------------------------------------------------------------------

@dataclass(frozen=True)
class RunOptions:
    """How the model is sampled."""

    steps: int | None = None      # None: the model's default
    sampler: str | None = None
    guidance: float = 0.0
    seed: int = 0
    ensemble: int | None = None   # None: the model's default


def model_size(relighter: Relighter, frames: np.ndarray) -> np.ndarray:
    """Frames [T,H,W,3] as the CLI and the studio hand them to the model: long side at its size."""
    return media.resize_frames(frames, relighter.spec.size, multiple=relighter.frame_multiple)


def brought_back(frames: np.ndarray, small: np.ndarray, output: np.ndarray) -> np.ndarray:
    """`output`, made by the model from `small` (the frames at its size), at the frames' size, the way
    the CLI and the studio return results (guided ratio upsampling); as it is when the sizes agree."""
    from relight_core.upsample import guided_ratio_upsample

    return output if small.shape == frames.shape else guided_ratio_upsample(frames, small, output)


def relight(relighter: Relighter, frames: np.ndarray, probe: np.ndarray, options: RunOptions
            ) -> tuple[np.ndarray, np.ndarray, float]:
    """(relit, albedo, seconds) of frames relit under a camera-frame probe, at the frames' size.

    Frames at another size than the model's go through the pipeline as the CLI and the studio run
    it: shrunk (or grown) to the model's size, relit there, and brought back by guided ratio
    upsampling (`upsample.guided_ratio_upsample`).
    """
    started = time.perf_counter()
    small = model_size(relighter, frames)
    result = relighter.relight(RelightRequest(
        small, mode="relight", camera_probe=probe, steps=options.steps, sampler=options.sampler,
        guidance=options.guidance, seed=options.seed, ensemble=options.ensemble))
    return (brought_back(frames, small, result.relit), brought_back(frames, small, result.albedo),
            time.perf_counter() - started)


def _compute(relighter: Relighter):
    return autocast(getattr(relighter, "dtype", torch.float32), relighter.device)


def _encode(relighter: Relighter, frames01: np.ndarray) -> torch.Tensor:
    """Frames [T,H,W,3] in [0,1] (a valid count) → latents [1,C,t,h,w], as `Relighter` encodes them."""
    video = torch.from_numpy(np.ascontiguousarray(frames01)).permute(3, 0, 1, 2)[None] * 2 - 1
    with torch.no_grad(), _compute(relighter):
        return relighter.tokenizer.encode(video.to(relighter.device)).float()


def _decode(relighter: Relighter, latents: torch.Tensor, length: int) -> np.ndarray:
    """Latents [1,C,t,h,w] → frames [length,H,W,3] in [0, 1]."""
    with torch.no_grad(), _compute(relighter):
        video = relighter.tokenizer.decode(latents).float()
    return ((video.clamp(-1, 1) + 1) / 2)[0].permute(1, 2, 3, 0).cpu().numpy()[:length]


def reconstruct(relighter: Relighter, frames01: np.ndarray) -> np.ndarray:
    """The tokenizer's encode → decode of frames [T,H,W,3] in [0, 1] at the model's size."""
    padded = pad_to_valid(frames01, relighter.tokenizer.temporal_factor)
    return _decode(relighter, _encode(relighter, padded), frames01.shape[0])


def ceiling(relighter: Relighter, truth: np.ndarray, frames: np.ndarray) -> np.ndarray:
    """The best the pipeline could return for `truth` given the input `frames` (both [T,H,W,3]): the
    tokenizer's reconstruction of the truth at the model's size, brought to the frames' size the way
    results are (guided ratio upsampling against the input) when that size differs."""
    return brought_back(frames, model_size(relighter, frames), reconstruct(relighter, model_size(relighter, truth)))


class _SigmaSweep:
    """A stand-in sampler: denoise the clean latents noised to each σ of the schedule, once each.

    Registered in `SAMPLERS` for one request, it receives the exact denoiser `Relighter` builds
    (conditions, lighting, masks) and never samples; it returns the last prediction.
    """

    def __init__(self, relighter: Relighter, item: EvalItem, seed: int):
        factor = relighter.tokenizer.temporal_factor
        self.relighter, self.item, self.seed = relighter, item, seed
        self.clean = torch.cat([_encode(relighter, pad_to_valid(x, factor))
                                for x in (item.input, item.target, item.albedo)], dim=2)   # (1, C, 3t, h, w)
        self.records: list[dict] = []

    def __call__(self, denoiser, x, sigmas, extra_args=None, callback=None):
        if x.shape != self.clean.shape:
            raise RuntimeError(f"the pipeline's latents {tuple(x.shape)} differ from the sweep's "
                               f"{tuple(self.clean.shape)}")
        clean = self.clean.to(x)
        t = clean.shape[2] // 3
        noise = torch.randn(clean.shape, generator=torch.Generator().manual_seed(self.seed)).to(x)
        frames = self.item.input.shape[0]
        for sigma in [s for s in sigmas.tolist() if s > 0]:    # a schedule's final 0 is no noise level
            x0 = denoiser(clean + sigma * noise, x.new_full((x.shape[0],), sigma), **(extra_args or {}))
            record = {"sigma": sigma}
            for name, third, truth in (("relit", 1, self.item.target), ("albedo", 2, self.item.albedo)):
                part = x0[:, :, third * t:(third + 1) * t]
                record[f"{name}_latent_mse"] = float(((part - clean[:, :, third * t:(third + 1) * t]) ** 2).mean())
                decoded = _decode(self.relighter, part.float(), frames)
                record[f"{name}_psnr"] = protocol_metrics(decoded, truth, self.item.mask)["psnr"]
            self.records.append(record)
        return x0


@contextmanager
def _registered(sampler):
    name = f"_evaluation-sweep-{id(sampler)}"
    SAMPLERS[name] = sampler
    try:
        yield name
    finally:
        SAMPLERS.pop(name, None)


def sigma_errors(relighter: Relighter, item: EvalItem, options: RunOptions, lighting: bool = True) -> list[dict]:
    """Per σ of the schedule: the denoiser's latent MSE and decoded protocol PSNR, relit and albedo.

    The item is cut to the model's first chunk and measured at the model's size; `lighting=False`
    zeroes the lighting (mode "random").
    """
    item = replace(item, **{k: getattr(item, k)[:relighter.spec.chunk_frames]
                            for k in ("input", "target", "albedo", "mask", "probe", "other_probe")})
    if model_size(relighter, item.input).shape != item.input.shape:
        item = resized(item, relighter.spec.size, relighter.frame_multiple)
    sweep = _SigmaSweep(relighter, item, options.seed)
    spec = relighter.spec
    relighter.spec = replace(spec, shift_average=1)     # the denoiser itself: one member, no shifted copies
    try:
        with _registered(sweep) as name:
            relighter.relight(RelightRequest(
                item.input, mode="relight" if lighting else "random", camera_probe=item.probe if lighting else None,
                steps=options.steps, sampler=name, seed=options.seed, ensemble=1))
    finally:
        relighter.spec = spec
    return sweep.records


# ---------------------------------------------------------------------------------------------
# Per-item measurements
# ---------------------------------------------------------------------------------------------

def probe_margin(result: np.ndarray, other_result: np.ndarray, item: EvalItem) -> float:
    """½[(P(r_B,t_B) − P(r_B,t_A)) + (P(r_A,t_A) − P(r_A,t_B))]; t_A = the input (module docstring)."""
    def p(pred, truth):
        return protocol_metrics(pred, truth, item.mask)["psnr"]

    return 0.5 * ((p(result, item.target) - p(result, item.input))
                  + (p(other_result, item.input) - p(other_result, item.target)))


def measure_item(relighter: Relighter, item: EvalItem, options: RunOptions, margin: bool = True
                 ) -> tuple[dict, dict]:
    """(metrics, outputs) of one item at its size: model, floor, ceiling (+ the margin)."""
    relit, albedo, seconds = relight(relighter, item.input, item.probe, options)
    out = {
        "name": item.name, "seconds": seconds,
        "model": {"relit": protocol_metrics(relit, item.target, item.mask),
                  "albedo": albedo_metrics(albedo, item.albedo, item.mask)},
        "floor": {"relit": protocol_metrics(item.input, item.target, item.mask),
                  "albedo": albedo_metrics(item.input, item.albedo, item.mask)},
        "ceiling": {"relit": protocol_metrics(ceiling(relighter, item.target, item.input), item.target, item.mask),
                    "albedo": albedo_metrics(ceiling(relighter, item.albedo, item.input), item.albedo, item.mask)},
    }
    if margin:
        other, _, _ = relight(relighter, item.input, item.other_probe, options)
        out["margin"] = probe_margin(relit, other, item)
    return out, {"relit": relit, "albedo": albedo}


def mean_metrics(records: list[dict], *path: str) -> dict | float | None:
    """The mean over records of the value (or dict of values) at `path`; None when none has it."""
    values = []
    for record in records:
        for key in path:
            record = record.get(key) if isinstance(record, dict) else None
        if record is not None:
            values.append(record)
    if not values:
        return None
    if isinstance(values[0], dict):
        return {k: mean_metrics(values, k) for k in values[0]}
    return float(np.mean(values))


def measure_full_resolution(relighter: Relighter, native: EvalItem, size: int, options: RunOptions,
                            reuse: tuple[np.ndarray, dict] | None = None) -> tuple[dict, dict]:
    """(metrics, outputs) at `size` px: the model's output brought up by plain resizing vs guided ratio.

    The item at `size` stands for the user's photo; the model sees it resized to its own size, as
    the CLI does. The oracle rows bring the ground truth, shrunk to the model's size, back up the
    same two ways: what each method could give with a perfect model. `reuse` = (model-size input,
    outputs) of a run already made on the same input.
    """
    from relight_core.upsample import guided_ratio_upsample, plain_upsample

    full = resized(native, size, multiple=1)

    small = model_size(relighter, full.input)
    if reuse is not None and reuse[0].shape == small.shape and np.array_equal(reuse[0], small):
        predicted = reuse[1]
    else:
        relit, albedo, _ = relight(relighter, small, full.probe, options)
        predicted = {"relit": relit, "albedo": albedo}
    H, W = full.input.shape[1:3]
    truths = {"relit": full.target, "albedo": full.albedo}
    metrics = {"name": native.name,
               "floor": {k: protocol_metrics(full.input, truth, full.mask) for k, truth in truths.items()}}
    outputs = {"input": full.input, "target": full.target}
    for source, smalls in (("model", predicted),
                           ("oracle", {k: model_size(relighter, truth) for k, truth in truths.items()})):
        metrics[source] = {}
        for key, truth in truths.items():
            plain = plain_upsample(smalls[key], H, W)
            guided = guided_ratio_upsample(full.input, small, smalls[key])
            metrics[source][key] = {"plain": protocol_metrics(plain, truth, full.mask),
                                    "guided": protocol_metrics(guided, truth, full.mask)}
            if source == "model" and key == "relit":
                outputs.update(plain=plain, guided=guided)
    return metrics, outputs
