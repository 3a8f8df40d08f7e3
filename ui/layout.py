"""The studio's page: controls on the left, results on the right, and the events that join them."""

from __future__ import annotations

import json
from pathlib import Path

import gradio as gr

from relight_core.diffusion import SAMPLERS
from relight_core.lighting import DEFAULT_ROTATION
from ui.studio import MODES, RANDOM_MODE, VIDEO_SUFFIXES, Studio, probe_choices, status_html

INPUT_TYPES = [".png", ".jpg", ".jpeg", ".webp", ".exr", ".mp4", ".mov", ".webm"]
PROBE_TYPES = [".hdr", ".exr"]
SIZES = [64, 128, 192, 256, 320, 384, 512, 640, 768, 848, 1024]
RESULT_HEIGHT = 300

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
                    "upload, pick a light, press **Relight**.")
        gr.Markdown(studio.model_notice(), elem_id="model-notice")
        with gr.Row(equal_height=False):
            # ------------------------------------------------------------------ controls
            with gr.Column(scale=5, min_width=340):
                input_file = gr.File(label="Image or video", file_types=INPUT_TYPES, type="filepath",
                                     elem_id="input-file", height=110)
                input_image = gr.Image(label="Input", interactive=False, height=220, elem_id="input-preview",
                                       buttons=[])
                input_video = gr.Video(label="Input video", interactive=False, height=220, visible=False)
                input_info = gr.Markdown("", elem_id="input-info")
                with gr.Row(visible=False) as frame_row:
                    frame_start = gr.Slider(0, 1, value=0, step=1, label="First frame")
                    frame_end = gr.Slider(0, 1, value=0, step=1, label="Last frame")
                size = gr.Dropdown(sizes, value=spec.size, label="Working resolution (long side, pixels)")
                estimate = gr.Markdown("Upload an image or a video to see the time estimate.",
                                       elem_id="estimate")
                mode = gr.Radio(list(MODES), value="Relight", label="What to make", elem_id="mode")
                num_seeds = gr.Slider(1, studio.config.max_seeds, value=4, step=1, visible=False,
                                      label="Number of random illuminations (seeds)")

                with gr.Group(elem_id="probe-panel"):
                    probe_gallery = gr.Gallery(
                        probe_choices(studio.probes), label="Light probe (click to pick)", columns=4,
                        height=190, allow_preview=False, object_fit="cover", elem_id="probe-gallery",
                        selected_index=names.index(default_probe) if default_probe else None, buttons=[])
                    probe_name = gr.Dropdown(names, value=default_probe, label="Selected probe",
                                             elem_id="probe-name")
                    probe_file = gr.File(label="…or upload your own (.hdr / .exr)", file_types=PROBE_TYPES,
                                         type="filepath", height=120, elem_id="probe-file")
                    no_probe = gr.Checkbox(False, label="No probe: random illumination")
                    rotation = gr.Slider(0, 360, value=DEFAULT_ROTATION, step=0.5, elem_id="rotation",
                                         label="Light rotation (yaw, degrees)")
                    exposure = gr.Slider(-6, 6, value=0, step=0.25, label="Light exposure (stops)")
                    rotate_light = gr.Checkbox(False, label="Rotate the light across the clip")
                    with gr.Row(visible=False) as sweep_row:
                        sweep_start = gr.Number(0, label="Sweep from (degrees)")
                        sweep_end = gr.Number(360, label="Sweep to (degrees)")
                    light_preview = gr.Image(label="Light preview", interactive=False, height=300,
                                             elem_id="light-preview", buttons=[], format="png")
                    gr.Markdown("A mirror ball and a matte ball lit by the probe as the model receives it; "
                                "below, the light all around the camera (the + marks where it looks).",
                                elem_id="light-caption")

                with gr.Accordion("Advanced", open=False):
                    steps = gr.Slider(1, 100, value=spec.steps, step=1, label="Sampling steps")
                    sampler = gr.Dropdown(list(SAMPLERS), value=spec.sampler, label="Sampler")
                    seed = gr.Number(0, precision=0, label="Seed (the same seed gives the same result)")
                    guidance = gr.Slider(0, 10, value=0, step=0.5, label="Guidance (0 = off, fastest)")
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
                       seeds_gallery, downloads])

        # ------------------------------------------------------------------ events
        input_file.change(studio.input_changed, input_file,
                          [input_image, input_video, frame_row, frame_start, frame_end, input_info],
                          api_name="inspect_input")
        input_file.change(_show_video_row, input_file, video_row, queue=False, api_visibility="private")
        estimate_inputs = [input_file, mode, frame_start, frame_end, size, steps, num_seeds, model]
        for component in (input_file, mode, frame_start, frame_end, size, steps, num_seeds):
            component.change(studio.estimate, estimate_inputs, estimate, trigger_mode="always_last",
                             api_visibility="private")

        mode.change(_mode_visibility, mode, [num_seeds, seeds_gallery, compare], queue=False, api_visibility="private")
        mode.input(lambda m: m == RANDOM_MODE, mode, no_probe, queue=False, api_visibility="private")
        no_probe.input(lambda on: RANDOM_MODE if on else "Relight", no_probe, mode, queue=False, api_visibility="private")
        rotate_light.change(lambda on: gr.update(visible=on), rotate_light, sweep_row, queue=False,
                            api_visibility="private")

        probe_gallery.select(studio.probe_picked, None, [probe_name, probe_file], queue=False, api_visibility="private")
        preview_inputs = [probe_name, probe_file, rotation, exposure, mode, rotate_light, sweep_start]
        # Renders follow the slider while it moves; "always_last" drops stale positions.
        rotation.change(studio.light_preview, preview_inputs, light_preview, trigger_mode="always_last",
                        concurrency_limit=2, concurrency_id="preview", api_name="light_preview")
        for component in (probe_name, probe_file, exposure, mode, rotate_light, sweep_start):
            component.change(studio.light_preview, preview_inputs, light_preview, trigger_mode="always_last",
                             concurrency_id="preview", api_visibility="private")
        demo.load(studio.light_preview, preview_inputs, light_preview, api_visibility="private")

        run_outputs = [status, out_input, out_relit, out_albedo, vid_input, vid_relit, vid_albedo, compare,
                       seeds_gallery, downloads]
        run_event = run.click(
            studio.run,
            [input_file, mode, probe_name, probe_file, rotation, exposure, rotate_light, sweep_start, sweep_end,
             num_seeds, frame_start, frame_end, size, steps, sampler, seed, guidance, model],
            run_outputs, api_name="relight", show_progress="hidden", concurrency_id="model")
        stop.click(studio.stop, None, status, cancels=[run_event], queue=False, api_name="stop")
    return demo


def launch_kwargs() -> dict:
    """Theme and CSS: Gradio 6 takes them at launch."""
    return {"theme": THEME, "css": CSS}


def _show_video_row(path: str | None):
    return gr.update(visible=bool(path) and Path(path).suffix.lower() in VIDEO_SUFFIXES)


def _mode_visibility(mode: str):
    random = mode == RANDOM_MODE
    return gr.update(visible=random), gr.update(visible=random), gr.update(visible=not random)


def _examples(studio: Studio, examples_dir: Path, input_file, probe_name, rotation, mode, outputs) -> None:
    """Example inputs whose results were computed once by scripts/make_examples.py."""
    manifest = json.loads((examples_dir / "manifest.json").read_text())
    manifest["root"] = str(examples_dir)
    rows = [[str(examples_dir / e["input"]), e["probe"], e["rotation"], e["mode"], e["name"]]
            for e in manifest["examples"]]
    example_name = gr.Textbox(visible=False, label="Example")
    gr.Examples(rows, [input_file, probe_name, rotation, mode, example_name],
                outputs, fn=lambda *values: studio.show_example(manifest, values[-1]),
                run_on_click=True, cache_examples=False, label="Examples (results cached on disk)")
