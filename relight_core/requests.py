"""What a `Relighter` takes and what it streams back: the request, its events and its result.

    Progress(...)   after every denoiser evaluation, with a cheap preview of the current x0
    ChunkDone(...)  when a chunk of a long video is decoded
    Finished(...)   once, with the stitched result
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Callable

import numpy as np
import torch

from relight_core import lighting

MODES = ("relight", "albedo", "render", "random")
MAX_SEED = 2**63 - 1  # seeds are 0 … 2⁶³−1 (a signed 64-bit integer)


@dataclass
class RelightRequest:
    """One relighting job. Frames are float32 [T,H,W,3] in [0,1] at the working resolution."""

    frames: np.ndarray
    fps: float | None = None
    audio_path: str | None = None
    audio_start: float = 0.0              # seconds into audio_path where the frames begin
    mode: str = "relight"                 # relight | albedo | render | random
    probe: torch.Tensor | np.ndarray | None = None  # linear lat-long [h,w,3]
    rotation: float = lighting.DEFAULT_ROTATION
    rotate_light: bool = False
    sweep: tuple[float, float] = (0.0, 360.0)
    intensity: float = 1.0
    temperature: float = lighting.NEUTRAL_KELVIN  # the light's colour temperature, K (lower = warmer)
    tint: float = 0.0                     # green (+) / magenta (−) shift of the light, Δuv within ±0.02
    camera_pitch: float = 0.0             # degrees the camera looks up (lighting.camera_rotation)
    camera_roll: float = 0.0              # degrees the camera is turned counter-clockwise about its view
    albedo: np.ndarray | None = None      # [T,H,W,3] for mode="render"
    # Linear panoramas already in the camera frame (the dataset's env*/ files): [H,W,3] for every
    # frame or [T,H,W,3] per frame, any size (re-gridded to the frames'). Used as given, in place of
    # probe/rotation/rotate_light/sweep; the intensity, temperature and tint still apply to it.
    camera_probe: torch.Tensor | np.ndarray | None = None
    steps: int | None = None              # None: the model's default
    sampler: str | None = None            # None: the model's default
    seed: int = 0
    guidance: float = 0.0
    ensemble: int | None = None           # samples averaged into the result; None: the model's default
    per_frame: bool = False               # True: a video's frames as the model made them, without the model's
                                          # temporal_filter (temporal.py)
    should_stop: Callable[[], bool] | None = None


@dataclass
class Progress:
    """One denoiser evaluation done."""

    evaluation: int           # 1-based network evaluation count within the chunk
    evaluations: int          # network evaluations per chunk: steps + 1 (steps for a model whose schedule
                              # ends at 0: ModelSpec.final_denoise), twice that with guidance
    chunk: int                # 0-based
    num_chunks: int
    relit_preview: np.ndarray   # [H,W,3] in [0,1], cheap linear decode of the current x0
    albedo_preview: np.ndarray
    eta_s: float              # seconds left for the whole request
    steps: int = 0            # the sampling steps asked for (0: one per evaluation)
    per_step: int = 0         # network evaluations a step: 1, 2 with guidance or heun, 4 with both (0: from
                              # evaluations and steps, for a one-call-a-step schedule with the clean-up call)

    @property
    def step(self) -> int:
        """The sampling step (1 … steps) this evaluation belongs to, as a person counts them: a
        final clean-x0 evaluation completes the last step."""
        if self.steps <= 0:
            return self.evaluation
        per_step = self.per_step or max(1, self.evaluations // (self.steps + 1))
        return min(self.steps, -(-self.evaluation // per_step))


@dataclass
class ChunkDone:
    """A chunk has been decoded; `relit`/`albedo` cover [start, start + len) of the video, and
    `stitched_relit`/`stitched_albedo` the whole video so far, [0, start + len), with the chunk
    cross-faded into the previous ones exactly as the final result will be — before the filter along time
    of a model with a `temporal_filter` (temporal.py), which needs the frames after them."""

    chunk: int
    num_chunks: int
    start: int
    relit: np.ndarray
    albedo: np.ndarray
    stitched_relit: np.ndarray
    stitched_albedo: np.ndarray


@dataclass
class RelightResult:
    """The stitched output of a request."""

    relit: np.ndarray          # [T,H,W,3] in [0,1]
    albedo: np.ndarray
    fps: float | None
    audio_path: str | None
    seed: int
    mode: str
    audio_start: float = 0.0
    seconds: float = 0.0
    info: dict = field(default_factory=dict)


@dataclass
class Finished:
    result: RelightResult


Event = Progress | ChunkDone | Finished
