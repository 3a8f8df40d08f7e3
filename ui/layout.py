"""The studio's page: controls on the left, results on the right, and the events that join them."""

from __future__ import annotations

import json
import math
from pathlib import Path

import gradio as gr

from relight_core.arguments import MAX_ENSEMBLE
from relight_core.diffusion import SAMPLERS
from relight_core.lighting import DEFAULT_ROTATION, MAX_PITCH_DEG, MAX_TINT, NEUTRAL_KELVIN
from ui.inputs import is_clip
from ui.probes import probe_choices
from ui.studio import Studio
from ui.views import CLEAR, CLEAR_COMPARE, MODE_VIEWS, MODES, RANDOM_MODE, RunOutputs, status_html

INPUT_TYPES = [".png", ".jpg", ".jpeg", ".webp", ".gif", ".exr", ".mp4", ".mov", ".webm"]
PROBE_TYPES = [".hdr", ".exr"]
SIZES = [64, 128, 192, 256, 320, 384, 512, 640, 768, 848, 1024]
RESULT_HEIGHT = 300
TEMPERATURES = (2000, 12000)  # the colour temperature slider's range, kelvin

CSS = """
.run-status { height: 46px; }
.run-bar { height: 10px; border-radius: 5px; background: var(--neutral-200); overflow: hidden; }
.run-bar > div { height: 100%; background: var(--color-accent); transition: width 0.2s; }
.run-status.done .run-bar > div { background: #2e9d5b; }
.run-status.stopped .run-bar > div { background: var(--neutral-400); }
.run-text { margin-top: 6px; font-size: 0.9em; white-space: nowrap; overflow: hidden; text-overflow: ellipsis; }
#light-preview img { object-fit: contain; }
#light-caption { font-size: 0.85em; padding: 0 8px; }
#out-input img, #out-relit img, #out-albedo img, #input-preview img {
  width: 100%; height: 100%; object-fit: contain; }
.field-error { color: var(--error-text-color, #b42318); background: var(--error-background-fill, #fef3f2);
  border: 1px solid var(--error-border-color, #fda29b); border-radius: 6px; padding: 6px 10px;
  font-weight: 600; }
.field-note { padding: 4px 10px; font-size: 0.95em; }
/* Inside a gr.Group, Gradio 6 draws images and galleries with a 3px text-coloured border; use a hairline. */
#probe-panel .block { border-width: 0; }
#probe-panel #probe-file { border-width: 1px; border-color: var(--border-color-primary); }
/* The probe gallery: every row in sight, each 2:1 thumbnail with its full name under it (no ellipsis). */
#probe-gallery .grid-container { grid-template-columns: repeat(var(--grid-cols), minmax(0, 1fr));
  grid-template-rows: none; grid-auto-rows: auto; padding-top: 30px; }
#probe-gallery .thumbnail-item { aspect-ratio: auto; height: auto; display: flex; flex-direction: column; }
#probe-gallery .thumbnail-item > img { aspect-ratio: 2 / 1; height: auto; object-fit: cover; }
#probe-gallery .caption-label { position: static; max-width: none; border: 0; border-radius: 0; background: none;
  padding: 2px 4px; text-align: center; white-space: normal; overflow: visible; text-overflow: clip;
  overflow-wrap: anywhere; line-height: 1.2; font-size: 0.85em; }
#probe-gallery .grid-wrap { overflow-y: visible; min-height: 0; max-height: none; height: auto; }
"""

THEME = gr.themes.Soft(primary_hue="orange", neutral_hue="slate")


def build_demo(studio: Studio, examples_dir: Path | None = None) -> gr.Blocks:
    """The Gradio Blocks of the studio; launch it with `launch_kwargs()` (theme, css)."""
    spec = studio.relighter().spec
    names = studio.probes.names
    default_probe = "studio" if "studio" in names else (names[0] if names else None)
    sizes = sorted(set(SIZES) | {spec.size})

    with gr.Blocks(title="UniRelight Studio", delete_cache=(600, 3600)) as demo:
        gr.Markdown("# UniRelight Studio\nRelight an image or a video with an HDR light probe: "
                    "upload, choose what to make and a light, then press the orange button.")
        gr.Markdown(studio.model_notice(), elem_id="model-notice")
        with gr.Row(equal_height=False):
            # ------------------------------------------------------------------ controls
            with gr.Column(scale=5, min_width=340):
                input_file = gr.File(label="Image or video", file_types=INPUT_TYPES, type="filepath",
                                     elem_id="input-file", height=110)
                # Right under the upload: its size and length, or in words why it cannot be used.
                input_info = gr.HTML("", elem_id="input-info")
                input_ok = gr.State(True)
                input_image = gr.Image(label="Input", interactive=False, height=220, elem_id="input-preview",
                                       buttons=[])
                input_video = gr.Video(label="Input video", interactive=False, height=220, visible=False,
                                       elem_id="input-video")
                with gr.Row(visible=False) as frame_row:
                    frame_start = FrameSlider(0, 1, value=0, step=1, label="First frame")
                    frame_end = FrameSlider(0, 1, value=0, step=1, label="Last frame")
                size_info = (f"The model was trained at {spec.size} px and works best there." if spec.trained
                             else f"The model's own size is {spec.size} px.") + (
                    " Results come back at your input's own resolution." if studio.config.full_resolution else "")
                size = gr.Dropdown(sizes, value=spec.size, label="Working resolution (long side, pixels)",
                                   info=size_info)
                estimate = gr.Markdown("Upload an image or a video to see the time estimate.",
                                       elem_id="estimate")
                mode = gr.Radio(list(MODES), value="Relight", label="What to make", elem_id="mode")
                num_seeds = gr.Slider(1, studio.config.max_seeds, value=4, step=1, visible=False,
                                      label="Number of random illuminations (seeds)", elem_id="num-seeds")

                with gr.Group(elem_id="probe-panel") as probe_panel:
                    # Tall enough for every row, so the picked probe is always in sight.
                    probe_gallery = gr.Gallery(
                        probe_choices(studio.probes), label="Light probe (click to pick)", columns=4,
                        height="auto", allow_preview=False, object_fit="cover",
                        elem_id="probe-gallery", buttons=[],
                        selected_index=names.index(default_probe) if default_probe else None)
                    # The bundled probe's name: the gallery sets it, examples and API clients too.
                    probe_name = gr.Dropdown(names, value=default_probe, label="Bundled probe", visible=False,
                                             elem_id="probe-name")
                    probe_file = gr.File(label="…or upload your own (.hdr / .exr)", file_types=PROBE_TYPES,
                                         type="filepath", height=120, elem_id="probe-file")
                    probe_info, probe_ok_value = studio.probe_status(default_probe, None)
                    probe_info = gr.HTML(probe_info, elem_id="probe-info")
                    probe_ok = gr.State(probe_ok_value)
                    rotation = gr.Slider(0, 360, value=DEFAULT_ROTATION, step=0.5, elem_id="rotation",
                                         label="Light rotation (yaw, degrees)")
                    exposure = gr.Slider(-6, 6, value=0, step=0.25, label="Light exposure (stops)")
                    temperature = gr.Slider(*TEMPERATURES, value=NEUTRAL_KELVIN, step=100, elem_id="temperature",
                                            label="Light colour temperature (kelvin)",
                                            info="6500 K is neutral; lower is warmer (orange), higher cooler (blue).")
                    tint = gr.Slider(-MAX_TINT, MAX_TINT, value=0.0, step=0.001, elem_id="tint",
                                     label="Light tint (Δuv)", info="0 is none; + greener, − more magenta.")
                    with gr.Row():
                        camera_pitch = gr.Slider(-MAX_PITCH_DEG, MAX_PITCH_DEG, value=0, step=0.5,
                                                 label="Camera pitch (degrees)", elem_id="camera-pitch",
                                                 info="How far the photo looks up (+) or down (−).")
                        camera_roll = gr.Slider(-45, 45, value=0, step=0.5, label="Camera roll (degrees)",
                                                elem_id="camera-roll",
                                                info="+ : the camera turned counter-clockwise.")
                    rotate_light = gr.Checkbox(False, label="Rotate the light across the clip", visible=False,
                                               elem_id="rotate-light")
                    with gr.Row(visible=False) as sweep_row:
                        sweep_start = gr.Number(0, label="Sweep from (degrees)")
                        sweep_end = gr.Number(360, label="Sweep to (degrees)")
                    light_preview = gr.Image(label="Light preview", interactive=False, height=300,
                                             elem_id="light-preview", buttons=[], format="png")
                    gr.Markdown("A mirror ball and a matte ball lit by the probe as the model receives it; "
                                "below, the light all around the camera (the + marks where it looks).",
                                elem_id="light-caption")
                # Never shown: they only give API clients the raising versions of page events.
                api_inspect = gr.Button(visible=False)
                api_preview = gr.Button(visible=False)

                with gr.Accordion("Advanced", open=False):
                    steps = gr.Slider(1, 100, value=spec.steps, step=1, label="Sampling steps")
                    sampler = gr.Dropdown(list(SAMPLERS), value=spec.sampler, label="Sampler")
                    seed = gr.Number(0, precision=0, label="Seed (the same seed gives the same result)")
                    guidance = gr.Slider(0, 10, value=0, step=0.5, label="Guidance (0 = off, fastest)")
                    ensemble = gr.Slider(1, MAX_ENSEMBLE, value=spec.ensemble, step=1, elem_id="ensemble",
                                         label="Samples averaged into the result",
                                         info="Each one adds a run; every second one sees the mirror image. "
                                              "More: steadier and a little more accurate, slower.")
                    model = gr.Textbox(studio.config.model, label="Model: 'default', a preset, or a model folder",
                                       interactive=studio.config.model_choice)

            # ------------------------------------------------------------------ results
            with gr.Column(scale=7, min_width=340):
                with gr.Row():
                    run = gr.Button("Relight", variant="primary", elem_id="run", scale=3)
                    stop = gr.Button("Stop", variant="stop", elem_id="stop", scale=1)
                status = gr.HTML(status_html(0.0, "Ready."), elem_id="status")
                with gr.Row(equal_height=True):
                    out_input = gr.Image(label="Input", interactive=False, height=RESULT_HEIGHT, format="png",
                                         elem_id="out-input")
                    out_relit = gr.Image(label="Relit", interactive=False, height=RESULT_HEIGHT, format="png",
                                         elem_id="out-relit")
                    out_albedo = gr.Image(label="Albedo", interactive=False, height=RESULT_HEIGHT, format="png",
                                          elem_id="out-albedo")
                with gr.Row(equal_height=True, visible=False) as video_row:
                    vid_input = gr.Video(label="Input clip", interactive=False, height=RESULT_HEIGHT)
                    vid_relit = gr.Video(label="Relit video", interactive=False, height=RESULT_HEIGHT,
                                         elem_id="vid-relit")
                    vid_albedo = gr.Video(label="Albedo video", interactive=False, height=RESULT_HEIGHT)
                compare = gr.ImageSlider(label="Before / after", interactive=False, max_height=420,
                                         elem_id="compare", format="png")
                seeds_gallery = gr.Gallery(label="Random illuminations (caption = seed; enter it under "
                                           "Advanced to reproduce)", columns=4, height=260, visible=False,
                                           elem_id="seeds")
                downloads = gr.File(label="Downloads", file_count="multiple", interactive=False,
                                    elem_id="downloads")

        if examples_dir is not None and (examples_dir / "manifest.json").is_file():
            _examples(studio, examples_dir, input_file, probe_name, rotation, mode,
                      [status, out_input, out_relit, out_albedo, vid_input, vid_relit, vid_albedo, compare,
                       seeds_gallery, downloads], [probe_file, exposure, temperature, camera_pitch, camera_roll, tint])

        # ------------------------------------------------------------------ events
        # The run button is named after the mode, and waits until the upload (and the probe, when the
        # mode uses one) can be used: the reason is shown beside that control, once.
        run_button_inputs = [mode, input_ok, probe_ok]
        input_shown = [input_image, input_video, frame_row, frame_start, frame_end, input_info]
        input_file.change(studio.input_checked, input_file, [*input_shown, input_ok],
                          api_visibility="private").then(_run_button, run_button_inputs, run, queue=False,
                                                         api_visibility="private")
        api_inspect.click(studio.input_changed, input_file, input_shown, api_name="inspect_input")
        input_file.change(_show_video_row, input_file, [video_row, rotate_light], queue=False,
                          api_visibility="private")
        estimate_inputs = [input_file, mode, frame_start, frame_end, size, steps, num_seeds, model, ensemble]
        for component in (input_file, mode, frame_start, frame_end, size, steps, num_seeds, ensemble):
            component.change(studio.estimate, estimate_inputs, estimate, trigger_mode="always_last",
                             api_visibility="private")

        mode.change(_mode_layout, mode,
                    [num_seeds, probe_panel, input_file, out_input, out_relit, out_albedo, vid_relit, vid_albedo,
                     compare, seeds_gallery], queue=False, api_visibility="private")
        mode.change(_run_button, run_button_inputs, run, queue=False, api_visibility="private")
        rotate_light.change(lambda on: gr.update(visible=on), rotate_light, sweep_row, queue=False,
                            api_visibility="private")

        probe_gallery.select(studio.probe_picked, None, [probe_name, probe_file], queue=False, api_visibility="private")

        def probe_checked(name, upload):
            info, ok = studio.probe_status(name, upload)
            if upload or name not in names:  # no bundled probe in use: none highlighted (the page drops a None)
                return info, ok, gr.update(selected_index=-1)
            return info, ok, gr.update(selected_index=names.index(name))

        for component in (probe_name, probe_file):
            component.change(probe_checked, [probe_name, probe_file], [probe_info, probe_ok, probe_gallery],
                             api_visibility="private").then(_run_button, run_button_inputs, run, queue=False,
                                                            api_visibility="private")
        page_preview_inputs = [probe_name, probe_file, rotation, exposure, rotate_light, sweep_start, temperature,
                               camera_pitch, camera_roll, tint]
        # Renders follow the slider while it moves; "always_last" drops stale positions. One render at a
        # time (the group's limit): two controls moved in quick succession would otherwise render side by
        # side and could finish out of order, leaving the older light on show. A probe that cannot be
        # used shows no preview here: probe_info says why.
        for component in (rotation, probe_name, probe_file, exposure, temperature, camera_pitch, camera_roll,
                          tint, rotate_light, sweep_start):
            component.change(studio.light_preview_quiet, page_preview_inputs, light_preview,
                             trigger_mode="always_last", concurrency_limit=1, concurrency_id="preview",
                             api_visibility="private")
        api_preview.click(studio.light_preview,
                          [probe_name, probe_file, rotation, exposure, mode, rotate_light, sweep_start, temperature,
                           camera_pitch, camera_roll, tint],
                          light_preview, concurrency_id="preview", api_name="light_preview")
        demo.load(studio.light_preview_quiet, page_preview_inputs, light_preview, api_visibility="private")

        run_outputs = [status, out_input, out_relit, out_albedo, vid_input, vid_relit, vid_albedo, compare,
                       seeds_gallery, downloads]
        run_event = run.click(
            studio.run,
            [input_file, mode, probe_name, probe_file, rotation, exposure, rotate_light, sweep_start, sweep_end,
             num_seeds, frame_start, frame_end, size, steps, sampler, seed, guidance, model, temperature,
             camera_pitch, camera_roll, tint, ensemble],
            run_outputs, api_name="relight", show_progress="hidden", concurrency_id="model")
        # A mode the user picks starts a new job: results made in another mode would sit under the wrong
        # labels (examples set the mode too, with their own results, hence .input, not .change).
        mode.input(_clear_results, None, run_outputs, queue=False, api_visibility="private")
        stop.click(studio.stop, None, status, cancels=[run_event], queue=False, api_name="stop")
    return demo


class FrameSlider(gr.Slider):
    """A frame-index slider whose range follows the uploaded video in the page, while API clients may
    send any whole frame number ≥ 0: the handlers check it against the video itself, so /relight
    accepts every valid range, not only the 0–1 of the slider's initial configuration."""

    is_template = True  # drawn by the frontend's plain slider

    def preprocess(self, payload: float) -> int:
        if payload is None or not math.isfinite(float(payload)) or float(payload) < 0:
            raise gr.Error(f"The frame number {payload} is not valid; use a whole number from 0.",
                           print_exception=False)
        return int(round(float(payload)))


def launch_kwargs() -> dict:
    """Theme and CSS: Gradio 6 takes them at launch."""
    return {"theme": THEME, "css": CSS}


def _show_video_row(path: str | None):
    """Video results, and the light sweep across the clip, only for a video (a still has no clip)."""
    video = is_clip(path)
    return gr.update(visible=video), gr.update(visible=video) if video else gr.update(visible=False, value=False)


def _mode_layout(mode: str):
    """Show only what `mode` uses: its controls, its results, with its labels (ui.views.MODE_VIEWS)."""
    view = MODE_VIEWS.get(mode, MODE_VIEWS["Relight"])
    random = mode == RANDOM_MODE
    return (gr.update(visible=random), gr.update(visible=view.uses_probe), gr.update(label=view.input_label),
            gr.update(label=view.input_result), gr.update(visible=bool(view.relit), label=view.relit or "Relit"),
            gr.update(visible=view.albedo),
            gr.update(visible=bool(view.relit), label=f"{view.relit or 'Relit'} video"),
            gr.update(visible=view.albedo), gr.update(visible=bool(view.compare), label=view.compare or ""),
            gr.update(visible=random))


def _clear_results():
    """Every result of the last run emptied (the input still stays), the status back to Ready."""
    return RunOutputs(status=status_html(0.0, "Ready."), relit_image=CLEAR, albedo_image=CLEAR, relit_video=CLEAR,
                      albedo_video=CLEAR, compare=CLEAR_COMPARE, seeds=CLEAR, downloads=CLEAR).values()


def _run_button(mode: str, input_ok: bool, probe_ok: bool):
    """The run button: named after the mode; it waits while the upload or the needed probe cannot be used."""
    view = MODE_VIEWS.get(mode, MODE_VIEWS["Relight"])
    return gr.update(value=view.button, interactive=bool(input_ok) and (bool(probe_ok) or not view.uses_probe))


def _examples(studio: Studio, examples_dir: Path, input_file, probe_name, rotation, mode, outputs,
              light_controls) -> None:
    """Example inputs whose results were computed once by scripts/make_examples.py. Clicking one also
    drops an uploaded probe and resets exposure, colour temperature, camera tilt and tint (`light_controls`),
    so the controls describe the cached result."""
    manifest = json.loads((examples_dir / "manifest.json").read_text())
    manifest["root"] = str(examples_dir)
    rows = [[str(examples_dir / e["input"]), e["probe"], e["rotation"], e["mode"], e["name"]]
            for e in manifest["examples"]]
    example_name = gr.Textbox(visible=False, label="Example")
    gr.Examples(rows, [input_file, probe_name, rotation, mode, example_name],
                [*outputs, *light_controls],
                fn=lambda *values: (*studio.show_example(manifest, values[-1]), None, 0, NEUTRAL_KELVIN, 0, 0, 0.0),
                run_on_click=True, cache_examples=False, label="Examples (results cached on disk)")
