"""Event handlers of the studio: they validate, call relight_core, and turn results into files.

No tensor maths lives here: frames are loaded, resized, relit, previewed and saved by
relight_core; the handlers only pick files, call the core and report errors in one sentence.
"""

from __future__ import annotations

import shutil
import threading
import time
import uuid
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import gradio as gr
import numpy as np

from relight_core import lighting, media, outputs, preview
from relight_core.colour import colour_science
from relight_core.errors import InputError
from relight_core.pipeline import ChunkDone, Finished, Progress, Relighter, RelightRequest
from ui.inputs import ANIMATION_SUFFIXES, frame_count, full_frames, is_video, load_frames, whole_number
from ui.probes import ProbeLibrary
from ui.views import (CLEAR, CLEAR_COMPARE, MODE_VIEWS, MODES, RANDOM_MODE, RunOutputs, _duration,
                      _progress_text, field_error, field_note, precision_note, status_html)

PREVIEW_SIDE = 640  # an animated image's upload is shown as an mp4 at most this long on a side


@dataclass(frozen=True)
class StudioConfig:
    """What the studio serves and where it keeps its files."""

    model: str = "default"              # "default", a preset name or a model directory
    precision: str | None = None        # auto | fp32 | bf16 | fp16; None: the model's (normally auto)
    envmaps_dir: Path = Path("envmaps")  # bundled probes
    work_dir: Path = Path("studio-work")  # per-job outputs, deleted once Gradio has copied them
    max_upload_mb: int = 500            # larger uploads are refused with a message
    max_seeds: int = 8                  # random illumination: at most this many seeds per run
    model_choice: bool = True           # may requests name another model than `model`?
    full_resolution: bool = True        # results at the input's resolution (guided ratio upsampling)


def _fail(exc: Exception, *paths: str | Path | None) -> gr.Error:
    """A user-facing error toast with the core's one-sentence message, server paths cut to file names."""
    message = str(exc)
    for path in paths:
        if path:
            message = message.replace(str(path), Path(path).name)
    return gr.Error(message, print_exception=False)


class Studio:
    """The studio's state shared by all sessions: the model, the probe library, stop flags."""

    def __init__(self, config: StudioConfig):
        self.config = config
        self.work_dir = Path(config.work_dir)
        self.work_dir.mkdir(parents=True, exist_ok=True)
        self.probes = ProbeLibrary(config.envmaps_dir, self.work_dir / "thumbnails")
        self._relighters: dict[str, Relighter] = {}
        self._model_lock = threading.Lock()
        self._stops: dict[str, threading.Event] = {}
        self.relighter(config.model)  # load at start: the first request should not wait for it
        colour_science()  # imported now (~2 s), not at the first EXR download or colour change

    # -- model ----------------------------------------------------------------------------------

    def relighter(self, model: str | None = None) -> Relighter:
        """The loaded model for `model` (one kept in memory at a time)."""
        model = (model or "").strip() or self.config.model
        if model != self.config.model and not self.config.model_choice:
            raise InputError("This studio serves a fixed model; restart it with --model to use another one.")
        with self._model_lock:
            if model not in self._relighters:
                self._relighters.clear()  # free the previous model before loading the next
                relighter = Relighter.load(model, precision=self.config.precision)
                relighter.warm_up()  # one-off costs paid now, and estimates from this machine's speed
                self._relighters[model] = relighter
            return self._relighters[model]

    def model_notice(self) -> str:
        """A visible line about the model in use (loud when its weights are untrained)."""
        relighter = self.relighter()
        spec = relighter.spec
        if not spec.trained:
            return (f"⚠️ Model **{spec.name}** has untrained (random) weights: results look like noise. "
                    f"Pass `--model DIR` with trained weights for real relighting. {precision_note(relighter)}")
        return f"Model: **{spec.name}** · {precision_note(relighter)}"

    # -- input ----------------------------------------------------------------------------------

    def check_upload(self, path: str | None) -> None:
        """Refuse files over the upload limit with a message (the web upload limit may be off)."""
        if path and Path(path).stat().st_size > self.config.max_upload_mb * 1024 * 1024:
            raise gr.Error(f"The file {Path(path).name} is larger than {self.config.max_upload_mb} MB; "
                           "upload a smaller or shorter file.", print_exception=False)

    def input_changed(self, path: str | None):
        """Show the upload at once; for videos, reveal the frame range set to the whole clip."""
        hidden = gr.update(visible=False)
        if not path:
            return gr.update(value=None, visible=True), gr.update(value=None, visible=False), hidden, \
                gr.update(), gr.update(), ""
        self.check_upload(path)
        try:
            if is_video(path):
                info = media.probe_video(path)
                if info.num_frames < 2:  # a one-value frame slider cannot be shown
                    raise InputError(f"{Path(path).name} has only {info.num_frames} frame; upload it as an "
                                     "image (PNG or JPEG) or upload a longer video.")
                last = info.num_frames - 1
                animation = Path(path).suffix.lower() in ANIMATION_SUFFIXES  # an animated GIF, APNG or WebP
                text = (f"{'Animation' if animation else 'Video'}: {info.width}×{info.height}, {info.num_frames} "
                        f"frames at {info.fps:.3g} fps{', with audio' if info.has_audio else ''}.")
                shown = path
                if animation:  # browsers play an mp4 of it
                    clip = media.load_video(path, size=None if max(info.width, info.height) <= PREVIEW_SIDE
                                            else PREVIEW_SIDE)
                    shown = str(self._job_dir("inputs") / "input.mp4")
                    media.save_video(shown, clip.frames, clip.fps)
                return (gr.update(value=None, visible=False), gr.update(value=shown, visible=True),
                        gr.update(visible=True),
                        gr.update(maximum=last, value=0), gr.update(maximum=last, value=last), text)
            loaded = media.load_media(path)
        except InputError as exc:
            raise _fail(exc, path) from exc
        shown = self._job_dir("inputs") / "input.png"
        media.save_image(shown, loaded.frames[0])
        height, width = loaded.frames.shape[1:3]
        return (gr.update(value=str(shown), visible=True), gr.update(value=None, visible=False), hidden,
                gr.update(), gr.update(), f"Image: {width}×{height}.")

    def input_checked(self, path: str | None):
        """`input_changed` for the page: a file that cannot be used is named in words under the upload
        (no toast), and the last value says whether the run may start."""
        try:
            *shown, info = self.input_changed(path)
        except gr.Error as exc:
            return (gr.update(value=None, visible=True), gr.update(value=None, visible=False),
                    gr.update(visible=False), gr.update(value=0), gr.update(value=0), field_error(exc.message), False)
        return (*shown, field_note(info) if info else "", True)

    def estimate(self, path: str | None, mode: str, frame_start: float, frame_end: float, size: int,
                 steps: float, num_seeds: float, model: str, ensemble: float | None = None) -> str:
        """The time estimate for the current choice, shown before running."""
        if not path:
            return "Upload an image or a video to see the time estimate."
        try:
            steps, num_seeds = whole_number(steps, "number of steps"), whole_number(num_seeds, "number of seeds")
            ensemble = None if ensemble is None else whole_number(ensemble, "number of samples averaged")
        except InputError as exc:
            return f"No time estimate: {exc}"
        try:
            relighter = self.relighter(model)
            frames = load_frames(path, frame_start, frame_start, size, relighter.frame_multiple).frames  # the size
            count = frame_count(path, frame_start, frame_end)
        except (InputError, OSError, gr.Error):
            return "No time estimate: the file above cannot be used."
        height, width = frames.shape[1:3]
        runs = int(num_seeds) if mode == RANDOM_MODE else 1
        try:
            seconds = runs * relighter.estimate_seconds(count, height, width, int(steps), ensemble)
        except InputError as exc:  # an ensemble out of range
            return f"No time estimate: {exc}"
        what = f"{count} frames" if count > 1 else "the image"
        return f"About **{_duration(seconds)}** for {what} at {width}×{height}, {int(steps)} steps" + \
            (f", {runs} seeds." if runs > 1 else ".")

    # -- probes ---------------------------------------------------------------------------------

    def probe_picked(self, evt: gr.SelectData):
        """A gallery click selects that bundled probe and drops any uploaded one."""
        return self.probes.entries[evt.index].name, None

    def probe_path(self, name: str | None, upload: str | None) -> Path | None:
        """The probe file to use: the upload if any, else the bundled probe by name."""
        if upload:
            self.check_upload(upload)
            return Path(upload)
        if name:
            try:
                return self.probes.path_of(name)
            except KeyError:
                raise gr.Error(f"There is no bundled probe called '{name}'; pick one from the gallery.",
                               print_exception=False) from None
        return None

    def probe_status(self, name: str | None, upload: str | None) -> tuple[str, bool]:
        """The line under the probe controls: the light in use, or in words why an uploaded probe
        cannot be used; and whether it can."""
        if upload:
            try:
                self.probes.load(self.probe_path(name, upload))
            except InputError as exc:
                return field_error(_fail(exc, upload).message), False
            except gr.Error as exc:
                return field_error(exc.message), False
            return field_note(f"Light: your probe **{Path(upload).name}** (the gallery is not used)"), True
        if name in self.probes.names:
            return field_note(f"Light: **{name}**"), True
        return field_error("Pick a light probe from the gallery or upload one."), False

    def light_preview(self, name: str | None, upload: str | None, rotation: float, exposure: float,
                      mode: str, rotate_light: bool = False, sweep_start: float = 0.0,
                      temperature: float = lighting.NEUTRAL_KELVIN, pitch: float = 0.0, roll: float = 0.0,
                      tint: float = 0.0):
        """The sphere + panorama preview of the probe at this rotation, exposure, colour temperature,
        camera tilt (pitch, roll) and tint."""
        if not MODE_VIEWS.get(mode, MODE_VIEWS["Relight"]).uses_probe:
            return None
        # What the first frame gets (lighting.frame_rotations: the slider's yaw plus the sweep's start).
        try:
            rotation = lighting.frame_rotations(1, float(rotation), bool(rotate_light),
                                                (float(sweep_start), 0.0))[0]
            temperature = lighting.check_temperature(temperature)
            tint = lighting.check_tint(tint)
            lighting.camera_rotation(pitch, roll)
        except InputError as exc:
            raise _fail(exc) from exc
        path = self.probe_path(name, upload)
        if path is None:
            return None
        try:
            probe = self.probes.load(path)
        except InputError as exc:
            raise _fail(exc, path) from exc
        return preview.render_preview(probe, float(rotation), intensity=2.0 ** float(exposure),
                                      temperature=temperature, pitch=float(pitch), roll=float(roll), tint=tint)

    def light_preview_quiet(self, name: str | None, upload: str | None, rotation: float, exposure: float,
                            rotate_light: bool, sweep_start: float, temperature: float, pitch: float = 0.0,
                            roll: float = 0.0, tint: float = 0.0):
        """`light_preview` for the page, where the panel is hidden in modes without a probe (so the mode
        does not matter): a probe that cannot be used shows no preview, and the line under the probe
        controls (`probe_status`) says why, so no second message appears."""
        try:
            return self.light_preview(name, upload, rotation, exposure, "Relight", rotate_light, sweep_start,
                                      temperature, pitch, roll, tint)
        except gr.Error:
            return None

    # -- run ------------------------------------------------------------------------------------

    def run(self, path: str | None, mode: str, probe_name: str | None, probe_upload: str | None,
            rotation: float, exposure: float, rotate_light: bool, sweep_start: float, sweep_end: float,
            num_seeds: float, frame_start: float, frame_end: float, size: int, steps: float, sampler: str,
            seed: float, guidance: float, model: str, temperature: float, camera_pitch: float,
            camera_roll: float, tint: float = 0.0, ensemble: float | None = None,
            request: gr.Request = None) -> Iterator[tuple]:
        """Relight the input; stream progress and previews, then the final files."""
        if not path:
            raise gr.Error("Upload an image or a video first.", print_exception=False)
        self.check_upload(path)
        stop = self._stops.setdefault(request.session_hash or "", threading.Event())
        stop.clear()
        job = self._job_dir("jobs")
        try:
            whole = {name: whole_number(value, label) for name, value, label in (
                ("num_seeds", num_seeds, "number of seeds"), ("frame_start", frame_start, "first frame"),
                ("frame_end", frame_end, "last frame"), ("size", size, "working size"),
                ("steps", steps, "number of steps"), ("seed", seed, "seed"))}
            members = None if ensemble is None else whole_number(ensemble, "number of samples averaged")
            yield from self._run(job, stop, path, MODES.get(mode, "relight"), probe_name, probe_upload,
                                 float(rotation), 2.0 ** float(exposure), bool(rotate_light),
                                 (float(sweep_start), float(sweep_end)), whole["num_seeds"], whole["frame_start"],
                                 whole["frame_end"], whole["size"], whole["steps"], sampler, whole["seed"],
                                 float(guidance), model, float(temperature), (float(camera_pitch), float(camera_roll)),
                                 float(tint), members)
        except InputError as exc:
            raise _fail(exc, path, probe_upload) from exc
        finally:
            # Gradio has copied every yielded file into its own cache by now.
            shutil.rmtree(job, ignore_errors=True)

    def stop(self, request: gr.Request) -> str:
        """Ask this session's run to stop at its next step."""
        self._stops.setdefault(request.session_hash or "", threading.Event()).set()
        return status_html(0.0, "Stopped.", "stopped")

    def _run(self, job: Path, stop: threading.Event, path, mode, probe_name, probe_upload, rotation,
             intensity, rotate_light, sweep, num_seeds, frame_start, frame_end, size, steps, sampler, seed,
             guidance, model, temperature=lighting.NEUTRAL_KELVIN, tilt=(0.0, 0.0), tint=0.0,
             ensemble=None) -> Iterator[tuple]:
        started = time.monotonic()
        view = MODE_VIEWS[next(label for label, name in MODES.items() if name == mode)]
        relighter = self.relighter(model)
        loaded = load_frames(path, frame_start, frame_end, size, relighter.frame_multiple)
        frames = loaded.frames
        is_video = loaded.is_video
        # An image's results come back at its own size from its frames; a video's from its file, a block of
        # frames at a time (`outputs.FullVideo`), so that a long one is never held at its own size.
        full = full_frames(path, frame_start, frame_end) if self.config.full_resolution and not is_video else None
        whole = outputs.FullVideo(str(path), int(frame_start), int(frame_end) + 1) \
            if self.config.full_resolution and is_video else None
        shown = frames if full is None else full
        probe = None
        if mode in ("relight", "render"):
            probe_file = self.probe_path(probe_name, probe_upload)
            if probe_file is None:
                raise InputError("Pick a light probe from the gallery or upload one, "
                                 "or choose 'Random illumination'.")
            probe = self.probes.load(probe_file)
        seeds = [seed + i for i in range(max(1, min(num_seeds, self.config.max_seeds)))] \
            if mode == "random" else [seed]

        audio = (loaded.audio_path, loaded.audio_start)
        # The still beside Relit and Albedo is the frame their stills show (a video's middle one).
        middle = frames.shape[0] // 2
        input_still = str(outputs.save_still(job / "input", shown[middle] if whole is None else whole.frame(middle)))
        input_clip = None
        if is_video:
            input_clip = str(outputs.save_clip(job / "input", shown if whole is None else whole.blocks(), True,
                                               loaded.fps, *audio, num_frames=frames.shape[0]))
        yield RunOutputs(status=status_html(0.0, "Starting: preparing the input and the light…"), input_image=input_still, input_video=input_clip,
                         relit_image=CLEAR, albedo_image=CLEAR, relit_video=CLEAR, albedo_video=CLEAR,
                         compare=CLEAR_COMPARE, downloads=CLEAR, seeds=[] if mode == "random" else None).values()

        gallery: list[tuple[str, str]] = []
        downloads: list[str] = []
        for run_index, run_seed in enumerate(seeds):
            request = RelightRequest(
                frames=frames, fps=loaded.fps, audio_path=loaded.audio_path, mode=mode, probe=probe,
                rotation=rotation, rotate_light=rotate_light, sweep=sweep, intensity=intensity,
                temperature=temperature, tint=tint, camera_pitch=tilt[0], camera_roll=tilt[1],
                albedo=frames if mode == "render" else None, steps=steps,
                sampler=sampler, seed=run_seed, guidance=guidance, ensemble=ensemble, should_stop=stop.is_set)
            result = None
            seed_started = time.monotonic()
            for event in relighter.run(request):
                if isinstance(event, Progress):
                    done = (run_index * event.num_chunks + event.chunk) * event.evaluations + event.evaluation
                    total = len(seeds) * event.num_chunks * event.evaluations
                    # The whole job's time left: this run's, plus each run still to come at this one's pace.
                    per_run = time.monotonic() - seed_started + event.eta_s
                    eta = event.eta_s + (len(seeds) - run_index - 1) * per_run
                    yield RunOutputs(
                        status=status_html(done / total, _progress_text(event, run_index, len(seeds), run_seed,
                                                                        eta)),
                        relit_image=self._save_preview(job, "relit-preview", event.relit_preview)
                        if view.relit else None,
                        albedo_image=self._save_preview(job, "albedo-preview", event.albedo_preview)
                        if view.albedo else None,
                    ).values()
                elif isinstance(event, ChunkDone) and is_video and event.num_chunks > 1 and view.relit:
                    # The video so far, its chunks cross-faded as in the final result.
                    partial = outputs.save_clip(job / f"relit-part{event.chunk}", event.stitched_relit, True,
                                                loaded.fps)
                    yield RunOutputs(relit_video=str(partial)).values()
                elif isinstance(event, Finished):
                    result = event.result
            if result is None:  # stopped
                yield RunOutputs(status=status_html(0.0, "Stopped.", "stopped")).values()
                return
            yield RunOutputs(status=status_html(
                (run_index + 1) / len(seeds), "Writing the results" +
                (" at the input's full resolution…" if full is not None or whole is not None else "…"))).values()
            # The mode's clips, at the input's full resolution (guided ratio upsampling; a video's a block at a time).
            files = {k: str(v) for k, v in outputs.write_outputs(
                outputs.result_clips(result, mode, frames, full), job, is_video, result.fps, *audio,
                suffix=f"-seed{run_seed}" if mode == "random" else "", stills=True, linear=("relit",),
                full=whole, working=frames).items()}
            made = outputs.MODE_OUTPUTS[mode]
            downloads += [files[name] for name in made] + [files[k] for k in ("relit_linear",) if k in files]
            if mode == "random":
                gallery.append((files["relit_still"], f"seed {run_seed}"))
            yield RunOutputs(
                status=status_html((run_index + 1) / len(seeds),
                                   f"Done in {_duration(time.monotonic() - started)}." if run_index + 1 == len(seeds)
                                   else f"Seed {run_seed} done.", "done" if run_index + 1 == len(seeds)
                                   else "running"),
                relit_image=files.get("relit_still"),
                albedo_image=files.get("albedo_still"),
                relit_video=files.get("relit") if is_video else None,
                albedo_video=files.get("albedo") if is_video else None,
                # A video's slider compares the middle frames, the stills shown beside it.
                compare=(input_still, files["relit_still"]) if view.compare else None,
                seeds=list(gallery) if mode == "random" else None,
                downloads=list(downloads),
            ).values()

    # -- examples -------------------------------------------------------------------------------

    def show_example(self, manifest: dict, name: str) -> tuple:
        """The cached results of one example, shown without running the model."""
        entry = next(e for e in manifest["examples"] if e["name"] == name)
        root = Path(manifest["root"])
        out = {k: str(root / v) for k, v in entry["outputs"].items()}
        video = entry.get("video", False)
        return RunOutputs(
            status=status_html(1.0, f"Cached example “{name}” (computed by scripts/make_examples.py).", "done"),
            input_image=None if video else str(root / entry["input"]),
            input_video=str(root / entry["input"]) if video else None,
            relit_image=out.get("relit_still"), albedo_image=out.get("albedo_still"),
            relit_video=out.get("relit_video"), albedo_video=out.get("albedo_video"),
            # Always set, so an earlier example's or run's before/after never stays on screen.
            compare=CLEAR_COMPARE if video else (str(root / entry["input"]), out["relit_still"]),
            seeds=CLEAR,
            downloads=[v for k, v in out.items() if k in entry.get("downloads", [])],
        ).values()

    # -- files ----------------------------------------------------------------------------------

    def _job_dir(self, kind: str, keep_s: float = 3600.0) -> Path:
        """A fresh folder under work_dir/kind; folders there older than keep_s are removed."""
        parent = self.work_dir / kind
        if parent.is_dir():
            now = time.time()
            for old in parent.iterdir():
                if now - old.stat().st_mtime > keep_s:
                    shutil.rmtree(old, ignore_errors=True)
        path = parent / uuid.uuid4().hex
        path.mkdir(parents=True)
        return path

    @staticmethod
    def _save_preview(job: Path, name: str, frame: np.ndarray) -> str:
        # A fresh name per step: the browser would otherwise keep showing a cached image.
        return str(outputs.save_still(job / f"{name}-{uuid.uuid4().hex[:8]}", frame))
