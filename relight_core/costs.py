"""What a request will cost before it runs: its time (from this machine's measured speed) and its
peak memory (refused in one sentence, before anything is allocated, when it cannot fit).

`Relighter` inherits these from `CostModel`; they read its model (`spec`, `dit`, `tokenizer`,
`device`) and the speed its last run measured (`_flops_per_second`, `_overhead_per_pixel`).
"""

from __future__ import annotations

import numpy as np
import torch

from relight_core.arguments import MAX_ENSEMBLE
from relight_core.chunking import plan_chunks
from relight_core.diffusion import network_calls
from relight_core.devices import free_memory, gb
from relight_core.dit import NUM_CLIPS
from relight_core.errors import InputError
from relight_core.requests import RelightRequest


class CostModel:
    """Time and memory estimates of `Relighter` requests (a mixin: see the module docstring)."""

    _flops_per_second: float | None = None  # measured on the last run
    _overhead_per_pixel: float | None = None  # seconds per frame pixel outside the network, measured

    def batch_members(self, ensemble) -> int:
        """The batch entries a request runs as one batch: its samples (`members`) × the model's copies at
        half-token shifts (`ModelSpec.shift_average`)."""
        return self.members(ensemble) * self.spec.shift_average

    def members(self, ensemble) -> int:
        """The samples a request averages (`RelightRequest.ensemble`; None: the model's `ensemble`);
        anything but a whole number from 1 to MAX_ENSEMBLE is one InputError sentence."""
        if ensemble is None:
            return self.spec.ensemble
        if isinstance(ensemble, bool) or not isinstance(ensemble, (int, np.integer)) \
                or not 1 <= ensemble <= MAX_ENSEMBLE:
            raise InputError(f"The ensemble takes a whole number of samples from 1 to {MAX_ENSEMBLE}, not {ensemble}.")
        return int(ensemble)

    def estimate_seconds(self, num_frames: int, height: int, width: int, steps: int | None = None,
                         ensemble: int | None = None) -> float:
        """Rough wall time of a request, from a measured (or assumed) cost per token."""
        steps = steps or self.spec.steps
        members = self.batch_members(ensemble)
        chunks = plan_chunks(num_frames, self.spec.chunk_frames, self.spec.overlap_frames)
        t = self.tokenizer.latent_frames(min(num_frames, self.spec.chunk_frames)) if num_frames > 1 else 1
        tokens = NUM_CLIPS * t * (height // self.frame_multiple) * (width // self.frame_multiple)
        per_eval = self._seconds_per_eval_at(tokens)
        overhead = (self._overhead_per_pixel or 0.0) * num_frames * height * width  # load, light, decode
        calls = network_calls(steps, self.spec.final_denoise, self.spec.sampler)
        return len(chunks) * calls * members * per_eval + overhead

    def warm_up(self) -> float:
        """Two small real runs (a grey image at the model's size up to 256 px, one step): the first pays
        the one-off costs so that the first request does not, the second measures this machine's speed
        for the estimates; returns their seconds."""
        side = min(self.spec.size, 256) // self.frame_multiple * self.frame_multiple or self.frame_multiple
        frames = np.full((1, side, side, 3), 0.5, dtype=np.float32)
        probe = torch.ones(16, 32, 3)
        return sum(self.relight(RelightRequest(frames, probe=probe, steps=1, rotation=angle)).seconds
                   for angle in (0.0, 90.0))  # two rotations: the second run encodes its lighting too

    def memory_estimate(self, num_frames: int, height: int, width: int, guidance: bool = False,
                        members: int = 1) -> tuple[int, int]:
        """Rough peak bytes of a request at this working size: (host arrays, model activations).

        Host: the clip's float32 frames, outputs and copies (≈ 6 arrays) plus one chunk's lighting
        panoramas and encodings (≈ 8). Model (on its device): the tokenizer's widest full-resolution
        stage (≈ 9 live tensors of its first width at H/2 × W/2, both output clips at once) and the DiT's
        ≈ (mlp_ratio + 12) float32 tensors of tokens × width (twice with guidance); both × the ensemble's
        `members`, which run as one batch. Attention runs
        through fused kernels, linear in the token count. Measured peaks (CPU, fp32) are within 15 %:
        tiny at 2048 px 0.94 GB, the default model at 1024 px 0.79 GB.
        """
        pixels = height * width
        chunk = min(num_frames, self.spec.chunk_frames)
        host = 6 * 12 * pixels * num_frames + 8 * 12 * pixels * chunk
        config = getattr(self.tokenizer, "config", None)
        first_width = getattr(config, "channels", (128,))[0]  # 128 for tokenizers that do not say
        tokenizer = 2 * 9 * first_width * (pixels // 4) * 4 * chunk * members
        t = self.tokenizer.latent_frames(chunk) if num_frames > 1 else 1
        tokens = NUM_CLIPS * t * max(1, height // self.frame_multiple) * max(1, width // self.frame_multiple)
        dit = tokens * self.spec.dit.width * (self.spec.dit.mlp_ratio + 12) * 4 * (2 if guidance else 1) * members
        return int(host), int(tokenizer + dit)

    def check_memory(self, num_frames: int, height: int, width: int, guidance: bool = False,
                     hint: str = "choose a smaller working size or fewer frames", members: int = 1) -> None:
        """Raise InputError, before anything is allocated, when a request cannot fit in this machine's memory."""
        host_free, device_free = free_memory(self.device)

        def fits(h: int, w: int) -> bool:
            host, model = self.memory_estimate(num_frames, h, w, guidance, members)
            if device_free is None:  # the model runs in host memory too
                return host + model <= host_free
            return host <= host_free and model <= device_free

        if fits(height, width):
            return
        host, model = self.memory_estimate(num_frames, height, width, guidance, members)
        need, free = (host + model, host_free) if device_free is None else \
            ((model, device_free) if model > device_free else (host, host_free))
        where = "this machine has" if device_free is None or need == host else f"{self.device} has"
        m, long_side = self.frame_multiple, max(height, width)
        low, high = 0, long_side // m  # largest long side (in multiples of m) that fits, same aspect
        while low < high:
            mid = (low + high + 1) // 2
            scale = mid * m / long_side
            if fits(max(m, round(height * scale / m) * m), max(m, round(width * scale / m) * m)):
                low = mid
            else:
                high = mid - 1
        frames = f"{num_frames} frame{'s' if num_frames != 1 else ''}"
        largest = (f"; at most about {low * m} pixels on the long side fit" if low else
                   "; even the smallest size does not fit, so use fewer frames")
        raise InputError(f"Working at {width}×{height} for {frames} needs about {gb(need)} of memory, but "
                         f"{where} {gb(free)} free{largest}: {hint}.")

    def _flops_per_eval(self, tokens: int) -> float:
        """Network FLOPs of one evaluation: 2·params per token plus attention's 4·L²·D a block."""
        params = sum(p.numel() for p in self.dit.parameters())
        return 2 * params * tokens + 4 * tokens * tokens * self.spec.dit.width * self.spec.dit.depth

    def _seconds_per_eval_at(self, tokens: int) -> float:
        """Seconds per evaluation at `tokens`, from the throughput of the last run when there was one."""
        throughput = self._flops_per_second or (2.5e11 if self.device.type == "cpu" else 2e14)
        return self._flops_per_eval(tokens) / throughput
