"""What the page shows, independent of any run: the modes and what each uses, one update of a run's
outputs, and the short texts (status bar, notes and errors beside a control, progress, durations)."""

from __future__ import annotations

import html
from dataclasses import dataclass

import gradio as gr

from relight_core.outputs import MODE_OUTPUTS
from relight_core.pipeline import Progress, Relighter

MODES = {  # label shown in the UI → pipeline mode
    "Relight": "relight",
    "Albedo only": "albedo",
    "Render from albedo": "render",
    "Random illumination": "random",
}
RANDOM_MODE = "Random illumination"


@dataclass(frozen=True)
class ModeView:
    """What the page shows in one mode: the run button's name, and which controls and results it uses.
    Which results a mode has is the core's `outputs.MODE_OUTPUTS`, the files the command line writes."""

    mode: str                    # the pipeline mode (MODES' values)
    button: str                  # the run button's label
    uses_probe: bool             # the probe panel (gallery, rotation, exposure, colour, preview)
    relit_label: str             # label of the relit result, when the mode makes one
    compare: str | None          # label of the before/after slider, None when hidden
    input_label: str = "Image or video"
    input_result: str = "Input"  # label of the input still beside the results

    @property
    def relit(self) -> str | None:
        """The relit result's label, None when the mode makes none."""
        return self.relit_label if "relit" in MODE_OUTPUTS[self.mode] else None

    @property
    def albedo(self) -> bool:
        """Whether the mode shows an albedo result."""
        return "albedo" in MODE_OUTPUTS[self.mode]


MODE_VIEWS = {
    "Relight": ModeView("relight", "Relight", True, "Relit", "Before / after"),
    "Albedo only": ModeView("albedo", "Extract albedo", False, "Relit", None),
    "Render from albedo": ModeView("render", "Render from albedo", True, "Rendered", "Albedo / rendered",
                                   input_label="Albedo image or video (rendered under the probe)",
                                   input_result="Albedo (input)"),
    RANDOM_MODE: ModeView("random", "Make random illuminations", False, "Relit (last seed)", None),
}
CLEAR = gr.update(value=None)  # a RunOutputs field set to this empties the component
CLEAR_COMPARE = gr.update(value=(None, None))  # the before/after slider emptied: no before, no after



@dataclass(frozen=True)
class RunOutputs:
    """What one update of a run sets: a file path, CLEAR, or None to leave the component as it is."""

    status: str | None = None
    input_image: object = None
    relit_image: object = None
    albedo_image: object = None
    input_video: object = None
    relit_video: object = None
    albedo_video: object = None
    compare: object = None                    # (before, after) image paths
    seeds: object = None                      # [(image path, "seed N"), ...]
    downloads: object = None                  # [file path, ...]

    def values(self) -> tuple:
        """The update as a tuple in the layout's output order, gr.skip() for unchanged fields.

        Update dicts (CLEAR, CLEAR_COMPARE) are copied: Gradio pops "value" out of the dict it is given,
        so a shared one would clear the component once and then never again.
        """
        return tuple(gr.skip() if v is None else dict(v) if isinstance(v, dict) else v for v in (
            self.status, self.input_image, self.relit_image, self.albedo_image, self.input_video,
            self.relit_video, self.albedo_video, self.compare, self.seeds, self.downloads))


def status_html(fraction: float, text: str, state: str = "running") -> str:
    """The progress bar and its one-line caption (fixed height, so nothing moves as it updates)."""
    percent = max(0.0, min(1.0, fraction)) * 100
    return (f'<div class="run-status {state}"><div class="run-bar"><div style="width:{percent:.1f}%"></div>'
            f'</div><div class="run-text">{text}</div></div>')


def precision_note(relighter: Relighter) -> str:
    """"fp32 (auto)": the precision the model computes in, and how it was chosen."""
    how = "auto, by this machine" if relighter.precision_choice == "auto" else "as asked"
    return f"Precision: **{relighter.precision}** ({how})"


def field_error(message: str) -> str:
    """A problem shown in words beside the control that has it (it stays until the control changes)."""
    return f'<div class="field-error" role="alert">⚠ {html.escape(message)}</div>'


def field_note(text: str) -> str:
    """A plain line beside a control (HTML; **bold** marks a name)."""
    parts = html.escape(text).split("**")
    return '<div class="field-note">' + "".join(
        f"<b>{p}</b>" if i % 2 else p for i, p in enumerate(parts)) + "</div>"


def _progress_text(event: Progress, run_index: int, runs: int, seed: int, eta_s: float | None = None) -> str:
    """What the bar says: the step of the steps chosen, the chunk and the seed, and the whole job's time left."""
    parts = [f"Step {event.step} of {event.steps or event.evaluations}"]
    if event.num_chunks > 1:
        parts.append(f"chunk {event.chunk + 1} of {event.num_chunks}")
    if runs > 1:
        parts.append(f"seed {seed} ({run_index + 1} of {runs})")
    parts.append(f"about {_duration(event.eta_s if eta_s is None else eta_s)} left")
    return " · ".join(parts)


def _duration(seconds: float) -> str:
    seconds = max(0.0, float(seconds))
    if seconds < 60:
        return f"{seconds:.0f} s" if seconds >= 1 else "under a second"
    minutes, rest = divmod(int(round(seconds)), 60)
    if minutes < 60:
        return f"{minutes} min {rest:02d} s"
    hours, minutes = divmod(minutes, 60)
    return f"{hours} h {minutes:02d} min"
