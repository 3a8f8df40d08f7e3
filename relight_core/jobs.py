"""One media job: relight, albedo, render or random illuminations of one image or video, from its
settings to files in a folder. The single-file commands (cli.py) and the batch runner (batch/)
both run jobs through these functions, so a batch row behaves exactly like the same command.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Callable, Iterable

import numpy as np
import torch

from relight_core import lighting, media
from relight_core.outputs import FullVideo, result_clips, write_outputs
from relight_core.pipeline import Event, Finished, Relighter, RelightRequest, RelightResult

PROBE_MODES = ("relight", "render")  # the modes that read a probe; the others ignore one


@dataclass(frozen=True)
class MediaJob:
    """What one job asks, as a command's flags or a batch row give it."""

    mode: str                                   # relight | albedo | render | random
    input: Path                                 # image or video (the albedo, for render)
    probe: Path | None = None                   # HDR probe (.exr / .hdr) for relight and render
    rotation: float | None = None               # yaw in degrees; None: the pipeline's default
    rotate_light: bool = False                  # sweep the yaw through 360° over the clip
    intensity: float = 1.0                      # multiplier on the probe's radiance
    temperature: float | None = None            # the light's colour temperature (K); None: neutral
    tint: float = 0.0                           # green (+) / magenta (−) shift of the light, Δuv
    camera_pitch: float = 0.0                   # degrees (lighting.camera_rotation)
    camera_roll: float = 0.0
    seeds: tuple[int, ...] = (0,)               # one result per seed
    steps: int | None = None                    # None: the model's
    sampler: str | None = None                  # None: the model's
    guidance: float = 0.0
    ensemble: int | None = None                 # samples averaged into each result; None: the model's
    size: int | None = None                     # working long side; None: the model's
    frames: tuple[int, int | None] = (0, None)  # frame range of a video, END exclusive
    raw: bool = False                           # write the model-size output (no guided upsampling)
    per_frame: bool = False                     # skip the model's temporal filter (RelightRequest.per_frame)


@dataclass(frozen=True)
class JobInputs:
    """A job's decoded input and probe. A video is not decoded here (`source` None, `video` its header):
    `plan_job` decodes it at the working size, and `write_job` writes its results at full resolution a block of
    frames at a time — memory for a block, not for the whole video at its own size (a 5 s 720p clip: 1.8 GB
    instead of 8.9, as fast), and no limit on its length but the working size's."""

    source: media.Media | None
    probe: torch.Tensor | None
    video: media.VideoInfo | None = None


@dataclass(frozen=True)
class JobPlan:
    """The working-size frames and the requests to run, each with its output-file prefix, and the input
    whose timing and sound the results take (`source`; a video's at the working size)."""

    frames: np.ndarray
    requests: list[tuple[str, RelightRequest]]
    source: media.Media


def load_inputs(job: MediaJob) -> JobInputs:
    """Decode the input and (for relight and render) the probe; bad files raise InputError."""
    start, end = job.frames
    probe = None
    if job.mode in PROBE_MODES and job.probe is not None:
        probe = lighting.load_probe(job.probe)  # the intensity goes on the request, as in the studio
    if media.media_kind(job.input) == "video":
        media.check_range(start, end)
        return JobInputs(None, probe, media.probe_video(job.input))
    return JobInputs(media.load_media(job.input, start=start, end=end), probe)


def _span(info: media.VideoInfo, start: int, end: int | None) -> int:
    """How many frames [start, end) holds by the header's count (the decode finds the true one)."""
    return max(min(info.num_frames if end is None else end, info.num_frames) - start, 1)


def plan_job(job: MediaJob, relighter: Relighter, inputs: JobInputs) -> JobPlan:
    """Check the job against the model and this machine's memory, then build its requests."""
    source = inputs.source
    size = job.size or relighter.spec.size
    if source is None:  # a video: its header says the size
        count, (height, width) = _span(inputs.video, *job.frames), (inputs.video.height, inputs.video.width)
    else:
        count, (height, width) = source.frames.shape[0], source.frames.shape[1:3]
    # Refuse a working size this machine cannot hold before allocating anything at that size.
    relighter.check_memory(count, *media.target_size(height, width, size, relighter.frame_multiple),
                           guidance=job.guidance > 0, hint="pass a smaller --size",
                           members=relighter.batch_members(job.ensemble))
    if source is None:
        start, end = job.frames
        source = media.load_media(job.input, start=start, end=end, size=size, multiple=relighter.frame_multiple)
    frames = media.resize_frames(source.frames, size, multiple=relighter.frame_multiple)
    base = dict(fps=source.fps, audio_path=source.audio_path, audio_start=source.audio_start, steps=job.steps,
                sampler=job.sampler, guidance=job.guidance, ensemble=job.ensemble, mode=job.mode, probe=inputs.probe,
                intensity=job.intensity, per_frame=job.per_frame)
    if job.rotation is not None:
        base["rotation"] = job.rotation
    if job.rotate_light:
        base["rotate_light"] = True
    if job.temperature is not None:
        base["temperature"] = lighting.check_temperature(job.temperature)  # out of range: one sentence
    if job.tint:
        base["tint"] = lighting.check_tint(job.tint)
    if job.camera_pitch or job.camera_roll:
        lighting.camera_rotation(job.camera_pitch, job.camera_roll)  # out of range: one sentence
        base["camera_pitch"], base["camera_roll"] = job.camera_pitch, job.camera_roll
    if job.mode == "render":
        base["albedo"] = frames
    # Random illuminations always name their seed; the other modes only when there are several.
    named = job.mode == "random" or len(job.seeds) > 1
    return JobPlan(frames, [(f"seed{seed:04d}_" if named else "", RelightRequest(frames, seed=seed, **base))
                            for seed in job.seeds], source)


def output_frames(job: MediaJob, source: media.Media, frames: np.ndarray, result: RelightResult
                  ) -> dict[str, np.ndarray]:
    """The clips a job writes (by name, `outputs.MODE_OUTPUTS`), at the input's resolution unless the
    job is raw."""
    return result_clips(result, job.mode, frames, None if job.raw else source.frames)


def save_outputs(clips: dict[str, np.ndarray], source: media.Media, folder: Path, prefix: str = ""
                 ) -> list[Path]:
    """Write each clip as `<prefix><name>.mp4` (videos, with the source's audio) or `.png` (images)."""
    return list(write_outputs(clips, folder, source.is_video, source.fps, source.audio_path, source.audio_start,
                              prefix).values())


def finished_result(label: str, events: Iterable[Event]) -> RelightResult:
    """Consume a request's events quietly and return its result."""
    for event in events:
        if isinstance(event, Finished):
            return event.result
    raise RuntimeError(f"{label}: the request ended without a result")


def write_job(job: MediaJob, relighter: Relighter, inputs: JobInputs, plan: JobPlan, folder: Path,
              follow: Callable[[str, Iterable[Event]], RelightResult] = finished_result) -> list[Path]:
    """Run every request of a planned job and write its outputs into `folder`; `follow(prefix, events)`
    consumes one request's events (e.g. to drive a progress bar) and returns its result."""
    written = []
    source = plan.source
    for prefix, request in plan.requests:
        result = follow(prefix, relighter.run(request))
        if source.is_video and not job.raw:  # at its own size from its file, a block at a time
            clips = result_clips(result, job.mode, plan.frames)
            written += list(write_outputs(clips, folder, True, source.fps, source.audio_path, source.audio_start,
                                          prefix, full=FullVideo(job.input, *job.frames),
                                          working=plan.frames).values())
        else:
            written += save_outputs(output_frames(job, source, plan.frames, result), source, folder, prefix)
    return written
