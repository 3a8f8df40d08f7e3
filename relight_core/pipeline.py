"""The `Relighter`: media frames + an HDR probe → relit frames and albedo, streamed.

One request runs as a generator of events so that callers (CLI, UI) can show progress and
previews and can stop at any point by closing the generator:

    Progress(...)   after every denoiser evaluation, with a cheap preview of the current x0
    ChunkDone(...)  when a chunk of a long video is decoded
    Finished(...)   once, with the stitched result

Videos longer than one chunk are cut into chunks of `spec.chunk_frames` frames that share
`spec.overlap_frames` frames. Each chunk after the first is conditioned on the previous chunk's
relit and albedo output over the shared frames (the tokenizer is causal, so the first
`overlap` frames of a chunk encode to exactly its first latent frames), and the shared frames are
cross-faded when stitching, so no seam shows.

The request, its events and result live in `requests.py` (re-exported here), the thread that turns
sampler callbacks into generator items in `streaming.py`, the device choice in `devices.py`, the
time and memory estimates in `costs.py`.
"""

from __future__ import annotations

import hashlib
import math
import time
from collections import OrderedDict
from typing import Iterator

import numpy as np
import torch

from relight_core import lighting, temporal
from relight_core.checkpoint import ModelSpec, load_model, load_refiner, resolve_model
from relight_core.chunking import crossfade_weights, pad_to_valid, plan_chunks, stitch
from relight_core.costs import CostModel
from relight_core.diffusion import (SAMPLERS, ConditionedDenoiser, EDMPrecond, calls_per_step, guided, network_calls,
                                    sampling_sigmas)
from relight_core.dit import LIGHTING_KEYS, NUM_CLIPS, network, pack_lighting
from relight_core.errors import InputError
from relight_core.precision import autocast, precision_name, resolve_precision
from relight_core.requests import (MAX_SEED, MODES, ChunkDone, Event, Finished, Progress,  # noqa: F401 (re-exported)
                                   RelightRequest, RelightResult)
from relight_core.devices import resolve_device  # noqa: F401 (re-exported)
from relight_core.streaming import Stopped, stream


# ---------------------------------------------------------------------------------------------
# The pipeline
# ---------------------------------------------------------------------------------------------

class Relighter(CostModel):
    """The UniRelight joint model behind one streaming API; see the module docstring (its time and
    memory estimates: `costs.CostModel`)."""

    def __init__(self, spec: ModelSpec, dit, tokenizer, device: str | torch.device = "cpu",
                 precision: str | None = None, refiner: torch.nn.Module | None = None,
                 relit_refiner: torch.nn.Module | None = None):
        self.spec = spec
        self.device = torch.device(device)
        # The hardware decides (precision.py), never the dtype the weights were stored in.
        self.precision_choice = precision or spec.precision          # what was asked: auto | fp32 | ...
        self.dtype = resolve_precision(self.precision_choice, self.device)
        self.precision = precision_name(self.dtype)                   # what runs: fp32 | bf16 | fp16
        # Weights in the compute dtype: under autocast no per-call weight casts, in fp32 no bf16 left over.
        self.dit = dit.to(self.dtype)
        self.tokenizer = _tokenizer_in(tokenizer, self.dtype)
        self.refiner = refiner  # refiner.Refiner (fp32 weights; runs under the autocast) or None
        self.relit_refiner = relit_refiner  # a second one (config "relit_refiner"), e.g. seeing the light
        self.denoiser = EDMPrecond(self._network)
        self._latent_cache: OrderedDict[str, torch.Tensor] = OrderedDict()
        self._preview_matrix: torch.Tensor | None = None
        self._flops_per_second: float | None = None  # measured on the last run
        self._overhead_per_pixel: float | None = None  # seconds per frame pixel outside the network, measured

    @classmethod
    def load(cls, model: str = "default", device: str | torch.device | None = None,
             precision: str | None = None) -> "Relighter":
        """Load "default", a preset name ("tiny", "small", "unirelight-7b") or a model directory.

        `precision` (auto | fp32 | bf16 | fp16) overrides the model's config; see precision.py.
        """
        device = resolve_device(device)  # a missing GPU or a typo is named, not blamed on the weights
        spec, directory = resolve_model(model)
        dtype = resolve_precision(precision or spec.precision, device)  # load straight into it
        spec, dit, tokenizer = load_model(model, device, dtype)
        return cls(spec, dit, tokenizer, device, precision, load_refiner(spec, directory, device),
                   load_refiner(spec, directory, device, "relit_refiner"))

    # -- public API -------------------------------------------------------------------------

    @property
    def frame_multiple(self) -> int:
        """Frame height and width must be multiples of this (tokenizer factor × patch size)."""
        return self.tokenizer.spatial_factor * self.spec.dit.patch_spatial

    def relight(self, request: RelightRequest) -> RelightResult:
        """Run a request to completion and return its result."""
        for event in self.run(request):
            if isinstance(event, Finished):
                return event.result
        raise InputError("The job was stopped before it finished.")

    def run(self, request: RelightRequest) -> Iterator[Event]:
        """Run a request, yielding Progress, ChunkDone and finally Finished events."""
        started = time.perf_counter()
        frames = self._validate(request)
        steps = request.steps or self.spec.steps
        sampler_name = request.sampler or self.spec.sampler
        num_frames, height, width = frames.shape[:3]
        chunks = plan_chunks(num_frames, self.spec.chunk_frames, self.spec.overlap_frames)
        rotations = lighting.frame_rotations(num_frames, request.rotation, request.rotate_light, request.sweep)
        probe = self._prepared_probe(request)
        members = self.members(request.ensemble)
        sigmas = sampling_sigmas(steps, self.spec.final_denoise).to(self.device)
        guidance_calls = 1 if request.guidance == 0 else 2    # the unconditional call beside each with guidance
        per_step = guidance_calls * calls_per_step(sampler_name)
        evals_per_chunk = guidance_calls * network_calls(steps, self.spec.final_denoise, sampler_name)

        relit_out = np.zeros_like(frames)
        albedo_out = np.zeros_like(frames)
        previous: tuple[int, np.ndarray, np.ndarray] | None = None  # (start, relit, albedo)
        steady = self.spec.temporal_filter[0] > 0 and num_frames > 1 and not request.per_frame  # temporal.py
        lit = steady and probe is not None and request.mode in ("relight", "render")   # the filter weighs the light
        lights: dict[int, np.ndarray] = {}   # frame → its target light's descriptor (temporal.light_descriptor)
        evals_done, total_evals = 0, len(chunks) * evals_per_chunk
        network_seconds: list[float] = []  # sampler time between previews: the network's share of the run
        eval_started = time.perf_counter()
        for index, (start, length) in enumerate(chunks):
            chunk_frames = frames[start:start + length]
            padded = pad_to_valid(chunk_frames, self.tokenizer.temporal_factor)
            albedo_in = None
            if request.mode == "render":
                albedo_in = pad_to_valid(request.albedo[start:start + length], self.tokenizer.temporal_factor)
            overlap = None
            if previous is not None:
                prev_start, prev_relit, prev_albedo = previous
                shared = prev_start + prev_relit.shape[0] - start
                overlap = (prev_relit[-shared:], prev_albedo[-shared:]) if shared > 0 else None
            rot = rotations[start:start + length]
            rot = rot + [rot[-1]] * (padded.shape[0] - len(rot))
            chunk_probe = probe
            if probe is not None and probe.dim() == 4:  # camera-frame panoramas: this chunk's, padded
                chunk_probe = probe[start:start + length]
                chunk_probe = torch.cat([chunk_probe, chunk_probe[-1:].expand(padded.shape[0] - length, -1, -1, -1)])
            if lit:
                for offset, descriptor in enumerate(self._light_descriptors(request, chunk_probe, rot[:length])):
                    lights[start + offset] = descriptor
            condition, mask, lighting_latents = self._members(
                request, padded, albedo_in, chunk_probe, rot, overlap, members)
            t = condition.shape[2] // NUM_CLIPS
            # Chunks that share no frames (an image model run frame by frame) share their noise, so
            # that consecutive frames are sampled alike and do not flicker.
            chunk_seed = index if self.spec.overlap_frames > 0 else 0
            generator = torch.Generator(device="cpu").manual_seed((request.seed * 1000003 + chunk_seed) % 2**64)
            noise = torch.randn(condition.shape, generator=generator).to(self.device)  # member 0 first
            cond_args = {"lighting": lighting_latents}
            uncond_args = {"lighting": torch.zeros_like(lighting_latents)}
            denoiser = ConditionedDenoiser(guided(self.denoiser, cond_args, uncond_args, request.guidance),
                                           condition, mask, residual=self.spec.residual,
                                           residual_gain=self.spec.residual_gain)
            sampler = SAMPLERS[sampler_name]

            def work(emit, _index=index, _t=t, _denoiser=denoiser, _noise=noise):
                network_started = time.perf_counter()

                def callback(info):
                    nonlocal evals_done, network_started
                    network_seconds.append(time.perf_counter() - network_started)  # since the last preview
                    evals_done += 1 if request.guidance == 0 else 2
                    elapsed = time.perf_counter() - eval_started
                    eta = elapsed / evals_done * (total_evals - evals_done)
                    relit_p, albedo_p = self._preview(info["denoised"], _t, height, width)
                    step = min(evals_done - _index * evals_per_chunk, evals_per_chunk)
                    emit(Progress(step, evals_per_chunk, _index, len(chunks), relit_p, albedo_p, eta, steps,
                                  per_step))
                    if request.should_stop is not None and request.should_stop():
                        raise Stopped
                    network_started = time.perf_counter()

                with torch.no_grad(), self._autocast():
                    return sampler(_denoiser, _noise * sigmas[0], sigmas, callback=callback)

            try:
                x0 = yield from stream(work)
            except Stopped:
                return
            relit_chunk, albedo_chunk = self._decode(x0, t, length)  # the members' mean
            light = self._refiner_light(request, chunk_probe, rot[:length], padded.shape[1], padded.shape[2])
            relit_chunk, albedo_chunk = self._refined(request.mode, chunk_frames, relit_chunk, albedo_chunk, light)
            weights = crossfade_weights(overlap[0].shape[0]) if overlap is not None else None
            stitch(relit_out, relit_chunk, start, weights)
            stitch(albedo_out, albedo_chunk, start, weights)
            previous = (start, relit_chunk, albedo_chunk)
            end = start + length
            yield ChunkDone(index, len(chunks), start, relit_chunk, albedo_chunk, relit_out[:end].copy(),
                            albedo_out[:end].copy())

        if steady:  # the results' frame-to-frame mistakes averaged where the input and its light hold still
            distances = temporal.light_distances(np.stack([lights[i] for i in range(num_frames)]),
                                                 self.spec.temporal_filter[0]) if lit else None
            relit_out, albedo_out = temporal.temporal_filter(frames, [relit_out, albedo_out], *self.spec.temporal_filter,
                                                             distances=distances)
        seconds = time.perf_counter() - started
        if evals_done:
            tokens = NUM_CLIPS * t * (height // self.frame_multiple) * (width // self.frame_multiple)
            network = sum(network_seconds) / self.batch_members(request.ensemble)  # one batch entry's sequence
            self._flops_per_second = evals_done * self._flops_per_eval(tokens) / max(network, 1e-6)
            self._overhead_per_pixel = max(seconds - network, 0.0) / (num_frames * height * width)
        yield Finished(RelightResult(relit_out, albedo_out, request.fps, request.audio_path, request.seed,
                                     request.mode, request.audio_start, seconds,
                                     {"chunks": len(chunks), "steps": steps, "sampler": sampler_name,
                                      "evaluations": evals_done, "ensemble": members, "model": self.spec.name,
                                      "precision": self.precision,
                                      "trained": self.spec.trained}))

    # -- request preparation ----------------------------------------------------------------

    def _validate(self, request: RelightRequest) -> np.ndarray:
        if request.mode not in MODES:
            raise InputError(f"Unknown mode '{request.mode}'; choose one of {', '.join(MODES)}.")
        frames = np.asarray(request.frames, dtype=np.float32)
        if frames.ndim != 4 or frames.shape[0] == 0 or frames.shape[-1] != 3:
            raise InputError("The input has no frames; load an image or a video with at least one frame.")
        _, height, width, _ = frames.shape
        m = self.frame_multiple
        if height % m or width % m:
            raise InputError(f"The frames are {width}×{height}, but both sides must be multiples of {m}; "
                             "resize them with media.resize_frames first.")
        if request.camera_probe is not None:
            shape = np.shape(request.camera_probe)
            if len(shape) not in (3, 4) or shape[-1] != 3 or (len(shape) == 4 and shape[0] != frames.shape[0]):
                raise InputError(f"The camera-frame probe has shape {list(shape)}; give [H,W,3] or one "
                                 f"panorama per frame, [{frames.shape[0]},H,W,3].")
        if request.mode in ("relight", "render") and request.probe is None and request.camera_probe is None:
            raise InputError(f"The '{request.mode}' mode needs an HDR probe; pick one, or choose the "
                             "'random' mode for random illuminations.")
        if request.mode == "render":
            if request.albedo is None or np.shape(request.albedo) != frames.shape:
                raise InputError("Rendering from albedo needs an albedo with the same frame count and size "
                                 "as the input; upload a matching albedo image or video.")
        if request.sampler is not None and request.sampler not in SAMPLERS:
            raise InputError(f"Unknown sampler '{request.sampler}'; choose one of {', '.join(SAMPLERS)}.")
        if request.steps is not None and not 1 <= request.steps <= 1000:
            raise InputError(f"Steps must be between 1 and 1000, not {request.steps}.")
        if not math.isfinite(request.guidance) or request.guidance < 0:
            raise InputError(f"Guidance must be a finite number ≥ 0, not {request.guidance}.")
        if not math.isfinite(request.intensity) or request.intensity <= 0:
            raise InputError(f"Intensity must be a positive number, not {request.intensity}.")
        lighting.check_temperature(request.temperature)
        lighting.check_tint(request.tint)
        lighting.camera_rotation(request.camera_pitch, request.camera_roll)  # refuses absurd angles
        if isinstance(request.seed, bool) or not isinstance(request.seed, (int, np.integer)) \
                or not 0 <= int(request.seed) <= MAX_SEED:
            raise InputError(f"The seed {request.seed} is out of range; use a whole number from 0 to {MAX_SEED}.")
        self.check_memory(frames.shape[0], height, width, guidance=request.guidance > 0,
                          members=self.batch_members(request.ensemble))
        return np.clip(frames, 0.0, 1.0)

    def _prepared_probe(self, request: RelightRequest) -> torch.Tensor | None:
        if request.mode in ("albedo", "random"):
            return None
        if request.camera_probe is not None:  # [T,H,W,3] at the frames' size, used as given
            num_frames, height, width = np.shape(request.frames)[:3]
            panoramas = torch.as_tensor(np.asarray(request.camera_probe, dtype=np.float32))
            panoramas = lighting.resize_panorama(panoramas, height, width)
            panoramas = panoramas.expand(num_frames, height, width, 3) if panoramas.dim() == 3 else panoramas
            return lighting.adjust_light(panoramas, request.intensity, request.temperature, request.tint).contiguous()
        if request.probe is None:
            return None
        probe = torch.as_tensor(np.asarray(request.probe, dtype=np.float32))
        return lighting.adjust_light(probe, request.intensity, request.temperature, request.tint)

    # -- latents ----------------------------------------------------------------------------

    def _encode(self, frames01: np.ndarray, cache: bool = True) -> torch.Tensor:
        """Frames [T,H,W,3] in [0,1] → latents [1,16,t,h,w]; cached by content."""
        key = None
        if cache:
            key = hashlib.sha1(frames01.tobytes() + str(frames01.shape).encode()).hexdigest()
            if key in self._latent_cache:
                self._latent_cache.move_to_end(key)
                return self._latent_cache[key]
        video = torch.from_numpy(np.ascontiguousarray(frames01)).permute(3, 0, 1, 2)[None] * 2 - 1
        with torch.no_grad(), self._autocast():
            latents = self.tokenizer.encode(video.to(self.device)).float()
        if key is not None:
            self._latent_cache[key] = latents
            while len(self._latent_cache) > 32:
                self._latent_cache.popitem(last=False)
        return latents

    def _encode_signed(self, video: torch.Tensor) -> torch.Tensor:
        """A [T,H,W,3] tensor already in [-1,1] → latents (lighting encodings)."""
        with torch.no_grad(), self._autocast():
            return self.tokenizer.encode(video.permute(3, 0, 1, 2)[None].to(self.device)).float()

    def _lighting_latents(self, probe: torch.Tensor, rotations: list[float], height: int, width: int,
                          camera: torch.Tensor | None = None, mirror: bool = False) -> torch.Tensor:
        """[1, 51, t, h, w]: (env_ldr, mask, env_log, mask, env_dir, mask) latents of one chunk;
        `camera` is the camera-to-world rotation (`lighting.camera_rotation`) of a tilted camera.
        `mirror`: the light of the left↔right mirrored scene, the camera panorama flipped u → 1 − u
        (env_dir, a direction per panorama pixel, stays), as training flips it (`training.fast`)."""
        tilt = None if camera is None else camera.tolist()
        key = hashlib.sha1(probe.numpy().tobytes()
                           + repr((rotations, height, width, tilt, mirror)).encode()).hexdigest()
        if key in self._latent_cache:
            self._latent_cache.move_to_end(key)
            return self._latent_cache[key]
        panoramas = lighting.lowpass_panorama(_camera_panoramas(probe, rotations, height, width, camera),
                                              self.spec.lighting_size)
        if mirror:
            panoramas = panoramas.flip(2)
        encodings = lighting.encode_lighting(panoramas)
        latents = pack_lighting(*(self._encode_signed(encodings[name]) for name in LIGHTING_KEYS))
        self._latent_cache[key] = latents
        return latents

    def _members(self, request, frames, albedo, probe, rotations, overlap, members: int):
        """`_conditions` for an ensemble of `members` samples, each run as `spec.shift_average` copies, all
        stacked on the batch axis (`_variants` orders them): condition [members·copies,16,3t,h,w], the shared
        mask [1,1,3t,1,1] and lighting [members·copies,51,t,h,w]. Member 0 is the plain request; every odd
        member is its mirror image (frames, albedo, the previous chunk's output and the light flipped
        left↔right, `_decode` flips its result back), each member with its own noise — averaging them
        estimates the posterior mean and cancels the model's left↔right bias. A copy sees those frames rolled
        by its shift (`_shifts`: half a DiT token, so the token grid falls elsewhere on the scene); `_decode`
        rolls its result back and leaves out the token row and column the roll wrapped across the border."""
        variants = self._variants(members)
        if variants == [(False, (0, 0))]:
            return self._conditions(request, frames, albedo, probe, rotations, overlap)

        def moved(x: np.ndarray | None, mirror: bool, shift: tuple[int, int]) -> np.ndarray | None:
            if x is None:
                return None
            x = _mirrored(x) if mirror else x
            return np.ascontiguousarray(np.roll(x, shift, axis=(1, 2))) if shift != (0, 0) else x

        built = [self._conditions(request, moved(frames, mirror, shift), moved(albedo, mirror, shift), probe,
                                  rotations, None if overlap is None else tuple(moved(x, mirror, shift) for x in overlap),
                                  mirror=mirror)
                 for mirror, shift in variants]
        return torch.cat([b[0] for b in built]), built[0][1], torch.cat([b[2] for b in built])

    def _shifts(self) -> list[tuple[int, int]]:
        """The (down, right) pixel shifts of a sample's `spec.shift_average` copies: half a DiT token."""
        return copy_shifts(self.spec.shift_average, self.frame_multiple)

    def _variants(self, members: int) -> list[tuple[bool, tuple[int, int]]]:
        """(mirrored, shift) of each batch entry of `members` samples: sample by sample, copy by copy."""
        return [(m % 2 == 1, shift) for m in range(members) for shift in self._shifts()]

    def _conditions(self, request, frames, albedo, probe, rotations, overlap, mirror: bool = False):
        """Condition latent [1,16,3t,h,w], its per-frame mask [1,1,3t,1,1] and lighting [1,51,t,h,w]
        (`mirror`: the light of the mirrored scene; the frames given are mirrored by the caller)."""
        z_input = self._encode(frames)
        _, c, t, h, w = z_input.shape
        zeros = torch.zeros_like(z_input)
        mask = torch.zeros(1, 1, NUM_CLIPS * t, 1, 1, device=self.device)
        if request.mode == "render":
            # Forward rendering: the albedo alone conditions the relit clip; the input is dropped.
            condition = torch.cat([zeros, zeros, self._encode(albedo)], dim=2)
            mask[:, :, :t] = 1.0
            mask[:, :, 2 * t:] = 1.0
        else:
            condition = torch.cat([z_input, zeros, zeros], dim=2)
            mask[:, :, :t] = 1.0
        if overlap is not None:
            # Continue the previous chunk: its output over the shared frames becomes a condition.
            # Only a causal prefix of 1 + j·factor shared frames maps onto whole latent frames.
            factor = self.tokenizer.temporal_factor
            usable = 1 + (overlap[0].shape[0] - 1) // factor * factor
            prev_relit, prev_albedo = overlap[0][:usable], overlap[1][:usable]
            z_relit, z_albedo = self._encode(prev_relit, cache=False), self._encode(prev_albedo, cache=False)
            k = z_relit.shape[2]
            condition[:, :, t:t + k] = z_relit
            mask[:, :, t:t + k] = 1.0
            if request.mode != "render":
                condition[:, :, 2 * t:2 * t + k] = z_albedo
                mask[:, :, 2 * t:2 * t + k] = 1.0
        if probe is None:
            lighting_latents = torch.zeros(1, 3 * (c + 1), t, h, w, device=self.device)
        else:
            camera = lighting.camera_rotation(request.camera_pitch, request.camera_roll)
            lighting_latents = self._lighting_latents(probe, rotations, frames.shape[1], frames.shape[2], camera,
                                                      mirror)
        return condition, mask, lighting_latents

    def _network(self, x_in: torch.Tensor, c_noise: torch.Tensor, lighting: torch.Tensor,
                 condition_mask: torch.Tensor) -> torch.Tensor:
        """The raw DiT on preconditioned input (`dit.network`, as training calls it)."""
        return network(self.dit, x_in, c_noise, lighting, condition_mask)

    # -- outputs ----------------------------------------------------------------------------

    def _decode(self, x0: torch.Tensor, t: int, length: int) -> tuple[np.ndarray, np.ndarray]:
        """Decode the relit and albedo clips of x0 to frames [length,H,W,3] in [0,1]; for an ensemble
        (`_members`) the mean of its entries, each put back in the request's place first (`copies_mean`)."""
        entries = x0.shape[0]
        clips = x0[:, :, t:].float()
        both = torch.cat([clips[:, :, :t], clips[:, :, t:]], dim=0)  # [2·entries, 16, t, h, w]
        with torch.no_grad(), self._autocast():
            video = self.tokenizer.decode(both).float()
        frames = ((video.clamp(-1, 1) + 1) / 2).permute(0, 2, 3, 4, 1).cpu().numpy()[:, :length]
        relit, albedo = frames[:entries], frames[entries:]
        if entries == 1:
            return relit[0], albedo[0]
        variants = self._variants(entries // self.spec.shift_average)
        return copies_mean(relit, variants, self.frame_multiple), copies_mean(albedo, variants, self.frame_multiple)

    def _light_descriptors(self, request: RelightRequest, probe: torch.Tensor, rotations: list[float]) -> np.ndarray:
        """[T,16,16,3]: each frame's target light as `temporal.light_distances` compares it — the camera-frame
        panoramas the DiT's lighting is made from (`_lighting_latents`), area-averaged."""
        camera = lighting.camera_rotation(request.camera_pitch, request.camera_roll)
        return temporal.light_descriptor(_camera_panoramas(probe, rotations, 32, 64, camera)[:len(rotations)])

    def _refiner_light(self, request: RelightRequest, probe: torch.Tensor | None, rotations: list[float],
                       height: int, width: int) -> torch.Tensor | None:
        """The target's camera-frame panoramas [T,s,s,3] on the model's lighting grid for a refiner that
        sees the light (None when none does, or there is no probe: a random light, albedo or render
        mode) — the probe the DiT's lighting is made from (`_lighting_latents`), one per frame."""
        if (probe is None or request.mode in ("render", "albedo")
                or not any(r is not None and r.config.lighting for r in (self.refiner, self.relit_refiner))):
            return None
        camera = lighting.camera_rotation(request.camera_pitch, request.camera_roll)
        panoramas = _camera_panoramas(probe, rotations, height, width, camera)[:len(rotations)]
        size = self.spec.lighting_size or 32
        return lighting.downsample_panorama(panoramas, min(size, panoramas.shape[1], panoramas.shape[2]))

    def _refiner_slots(self, lit: bool = True) -> list[str]:
        """The slots ("refiner", "relit_refiner", in that order) whose refiner runs: the model has it and,
        with `lit` False (a random light), it does not need the light."""
        return [slot for slot in ("refiner", "relit_refiner")
                if getattr(self, slot) is not None and (lit or not getattr(self, slot).config.lighting)]

    def clip_refiners(self, lit: bool = True) -> dict[str, str]:
        """{clip: the slot ("refiner", "relit_refiner") of the refiner whose result that clip ("relit",
        "albedo") is}: each refiner corrects its clips, and where both correct one the relit refiner's wins.
        With `lit` False (a random light) a refiner that sees the light is left out. A clip no refiner
        corrects is not listed."""
        owners = {}
        for slot in self._refiner_slots(lit):     # the later one wins
            owners.update({clip: slot for clip in getattr(self, slot).config.clips})
        return {clip: owners[clip] for clip in ("relit", "albedo") if clip in owners}

    def _refined(self, mode: str, frames: np.ndarray, relit: np.ndarray, albedo: np.ndarray,
                 light: torch.Tensor | None = None) -> tuple[np.ndarray, np.ndarray]:
        """The relit and albedo frames [T,H,W,3] in [0, 1] after the model's refiners (refiner.py: they
        sharpen what the DiT made, looking at the input; one may see the target light `light`, the
        chunk's camera-frame panoramas [T,s,s,3] from `_refiner_light`) or, for a model without one, its
        offset filter (`_smoothed`). Each refiner corrects its clips from the same frames (`clip_refiners`:
        the relit refiner's win where both correct one); a clip none corrects comes back as the first one's base.
        A refiner that sees the light is left out when there is none (a random light). Not in render
        mode, whose outputs do not start from an input photo."""
        slots = self._refiner_slots(light is not None)
        refiners = [getattr(self, slot) for slot in slots]
        if not refiners or mode == "render":
            return self._smoothed(mode, frames, relit, albedo)

        def signed(x: np.ndarray) -> torch.Tensor:
            return torch.from_numpy(np.ascontiguousarray(x)).float().permute(0, 3, 1, 2).to(self.device) * 2 - 1

        def unsigned(parts: list[torch.Tensor]) -> np.ndarray:
            return ((torch.cat(parts) + 1) / 2).clamp(0, 1).permute(0, 2, 3, 1).cpu().numpy().astype(relit.dtype)

        filtered = (self._smoothed(mode, frames, relit, albedo)
                    if any(r.config.base == "filtered" for r in refiners) else None)
        refined = [([], []) for _ in refiners]     # per refiner: its relit and albedo parts
        with torch.no_grad(), self._autocast():
            for start in range(0, len(frames), 8):  # a few frames at a time: memory stays flat for long clips
                part = slice(start, start + 8)
                given = None if filtered is None else (signed(filtered[0][part]), signed(filtered[1][part]))
                inputs = signed(frames[part]), signed(relit[part]), signed(albedo[part])
                for refiner, (relit_parts, albedo_parts) in zip(refiners, refined):
                    r, a = refiner.refine(*inputs, given if refiner.config.base == "filtered" else None,
                                          light[part].to(self.device) if refiner.config.lighting else None)
                    relit_parts.append(r.float())
                    albedo_parts.append(a.float())
        out = list((relit, albedo) if refiners[0].config.base == "raw" else filtered)
        for clip, slot in self.clip_refiners(light is not None).items():   # the others come back exactly as they were
            k = ("relit", "albedo").index(clip)
            out[k] = unsigned(refined[slots.index(slot)][k])
        return out[0], out[1]

    def _smoothed(self, mode: str, frames: np.ndarray, relit: np.ndarray, albedo: np.ndarray
                  ) -> tuple[np.ndarray, np.ndarray]:
        """The relit and albedo frames with a residual model's offset filter (`ModelSpec.offset_filter`),
        its radii scaled from the model's size to these frames' size. Not in render mode: there the
        offsets do not start from an input."""
        if not self.spec.residual or mode == "render" or not any(self.spec.offset_filter):
            return relit, albedo
        from relight_core.upsample import smooth_offset  # opencv, loaded when a model asks for it
        scale = max(frames.shape[1:3]) / self.spec.size
        radii = [max(1, round(r * scale)) if r > 0 else 0 for r in self.spec.offset_filter]
        return smooth_offset(frames, relit, radii[0]), smooth_offset(frames, albedo, radii[1])

    def _preview(self, x0: torch.Tensor, t: int, height: int, width: int) -> tuple[np.ndarray, np.ndarray]:
        """Cheap preview of the first latent frame of each clip: the exact decode where the tokenizer's
        decode is cheap (the pixel tokenizer), else a fitted linear map latent → RGB."""
        if getattr(self.tokenizer, "decode_is_cheap", False):
            frames = [self.tokenizer.decode(x0[:, :, clip * t:clip * t + 1].float())[0, :, 0] for clip in (1, 2)]
            return tuple(((f.clamp(-1, 1) + 1) / 2).permute(1, 2, 0).cpu().numpy() for f in frames)
        matrix = self._latent_to_rgb()
        out = []
        for clip in (1, 2):
            latent = x0[0, :, clip * t].float()                                  # [16, h, w]
            rgb = torch.einsum("chw,cd->dhw", torch.cat([latent, torch.ones_like(latent[:1])]), matrix).float()
            rgb = torch.nn.functional.interpolate(rgb[None], size=(height, width), mode="bilinear",
                                                  align_corners=False)[0]
            out.append(rgb.clamp(0, 1).permute(1, 2, 0).cpu().numpy())
        return out[0], out[1]

    def _latent_to_rgb(self) -> torch.Tensor:
        """[17, 3] least-squares map from (latent, 1) to the mean colour of each latent pixel."""
        if self._preview_matrix is None:
            size = 8 * self.frame_multiple
            generator = torch.Generator().manual_seed(0)
            blocks = torch.rand(3, 3, size // 16, size // 16, generator=generator)
            images = torch.nn.functional.interpolate(blocks, size=(size, size), mode="nearest")  # [3,3,S,S]
            latents = torch.cat([self._encode_signed(img.permute(1, 2, 0)[None] * 2 - 1) for img in images])
            f = self.tokenizer.spatial_factor
            target = torch.nn.functional.avg_pool2d(images, f)                   # [3,3,S/f,S/f]
            a = latents[:, :, 0].permute(0, 2, 3, 1).reshape(-1, latents.shape[1])
            a = torch.cat([a, torch.ones_like(a[:, :1])], dim=1)
            b = target.permute(0, 2, 3, 1).reshape(-1, 3).to(a)
            self._preview_matrix = torch.linalg.lstsq(a.cpu(), b.cpu()).solution.to(self.device)
        return self._preview_matrix

    def _autocast(self):
        """Autocast for bf16/fp16, nothing for fp32."""
        return autocast(self.dtype, self.device)


def _camera_panoramas(probe: torch.Tensor, rotations: list[float], height: int, width: int,
                      camera: torch.Tensor | None) -> torch.Tensor:
    """The target light of a chunk as camera-frame panoramas [T,h,w,3], one per frame: the probe turned by
    each frame's rotation and seen from the (tilted) camera, or `probe` itself when it is already the
    chunk's camera-frame panoramas (`RelightRequest.camera_probe`, 4-d). What the DiT's lighting and a
    refiner that sees the light are both made from."""
    if probe.dim() == 4:
        return probe
    return torch.stack([lighting.probe_in_camera(probe, height, width, rotation=r, cam_to_world=camera)
                        for r in rotations])


def _mirrored(frames: np.ndarray) -> np.ndarray:
    """Frames [T,H,W,3] flipped left↔right."""
    return np.ascontiguousarray(frames[:, :, ::-1])


def _tokenizer_in(tokenizer, dtype: torch.dtype):
    """The tokenizer set up for compute in `dtype`: a module keeps fp32 weights (autocast lowers them
    where it runs), a TorchScript one (Cosmos) is cast to `dtype` itself, whatever its config stored."""
    if isinstance(tokenizer, torch.nn.Module):
        return tokenizer.float()
    if hasattr(tokenizer, "set_dtype"):
        tokenizer.set_dtype(dtype)
    return tokenizer


def copy_shifts(copies: int, token: int) -> list[tuple[int, int]]:
    """The (down, right) pixel shifts of a sample's `copies` (`ModelSpec.shift_average`): half a DiT token of
    `token` pixels, so the token grid falls elsewhere on the scene in each."""
    half = token // 2
    return [(0, 0), (half, half), (half, 0), (0, half)][:copies]


def copies_mean(entries: np.ndarray, variants: list[tuple[bool, tuple[int, int]]], token: int) -> np.ndarray:
    """The mean of an ensemble's entries [E,...,H,W,C], entry k made as `variants[k]` (mirrored, (down, right)
    shift) — each rolled back and, if mirrored, flipped back; a shifted copy not counting in the token row and
    column its roll wrapped across the border (half a token at each edge of the frame, which the unshifted
    entries fill; there must be one)."""
    height, width = entries.shape[-3:-1]
    masks = []
    for _, (down, right) in variants:
        # the first token row (column) of a copy rolled down (right) holds the strip rolled in from the other
        # side next to the scene's edge: neither part saw its true neighbours
        valid = np.ones((height, width, 1), np.float32)
        valid[:token if down else 0], valid[:, :token if right else 0] = 0, 0
        masks.append(valid)
    weight = sum(_undone(valid, variant) for valid, variant in zip(masks, variants))
    return sum(_undone(entry * valid, variant) for entry, valid, variant in zip(entries, masks, variants)) / weight


def _undone(image: np.ndarray, variant: tuple[bool, tuple[int, int]]) -> np.ndarray:
    """An entry's frames [...,H,W,C] back in the request's place: rolled back, then flipped back if mirrored."""
    mirror, (down, right) = variant
    image = np.roll(image, (-down, -right), axis=(-3, -2))
    return image[..., ::-1, :] if mirror else image
