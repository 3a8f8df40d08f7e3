"""What an evaluation writes for people: metrics.md tables and image grids."""

from __future__ import annotations

import os
from pathlib import Path

os.environ.setdefault("OPENCV_IO_ENABLE_OPENEXR", "1")  # must precede the cv2 import

import cv2  # noqa: E402
import numpy as np  # noqa: E402

from relight_core import media  # noqa: E402

PROTOCOL = ("PSNR (dB) / SSIM of display values in [0, 1] after a per-channel least-squares scale fit "
            "on the foreground mask; PSNR over mask pixels, SSIM (11×11 Gaussian) over windows centred "
            "on mask pixels; per frame, averaged over frames, then over items (both directions of each "
            "scene). Albedo ΔE2000: the mean CIEDE2000 colour difference (colour-science; sRGB display "
            "values → CIE Lab, D65 white) over mask pixels of the same scale-fitted albedo, per frame, "
            "averaged over frames, then over items. The lighting is the dataset's camera-frame panorama "
            "of the target probe.")
LABEL_HEIGHT = 14
MIN_TILE = 128     # pixels: grid tiles are at least this wide


def _frame_rows(num_frames: int) -> list[int]:
    return sorted({0, num_frames // 2, num_frames - 1})


def _grid(columns: list[tuple[str, np.ndarray]], path: Path) -> None:
    """Columns of [T,H,W,3] frames side by side, rows = first, middle and last frame, labels on top."""
    frames = _frame_rows(columns[0][1].shape[0])
    zoom = -(-MIN_TILE // columns[0][1].shape[2])  # small frames are enlarged (nearest) so labels fit
    columns = [(label, images[frames].repeat(zoom, axis=1).repeat(zoom, axis=2)) for label, images in columns]
    frames = range(len(frames))
    height, width = columns[0][1].shape[1:3]
    header = np.ones((LABEL_HEIGHT, width * len(columns), 3), np.float32)
    for c, (label, _) in enumerate(columns):
        cv2.putText(header, label, (c * width + 3, LABEL_HEIGHT - 4), cv2.FONT_HERSHEY_SIMPLEX, 0.33,
                    (0.0, 0.0, 0.0), 1, cv2.LINE_AA)
    rows = [np.concatenate([np.clip(images[t], 0, 1) for _, images in columns], axis=1) for t in frames]
    media.save_image(path, np.concatenate([header, *rows], axis=0))


def save_grid(path: Path, item, outputs: dict) -> None:
    """input | target | relit | albedo target | albedo, at the model's size."""
    _grid([("input", item.input), ("target", item.target), ("relit", outputs["relit"]),
           ("albedo target", item.albedo), ("albedo", outputs["albedo"])], path)


def save_full_grid(path: Path, outputs: dict) -> None:
    """input | target | relit (plain resize) | relit (guided ratio), at the evaluation size."""
    _grid([("input", outputs["input"]), ("target", outputs["target"]), ("relit, plain resize", outputs["plain"]),
           ("relit, guided ratio", outputs["guided"])], path)


# ---------------------------------------------------------------------------------------------
# metrics.md
# ---------------------------------------------------------------------------------------------

def _pair(metrics: dict | None) -> str:
    if not metrics:
        return "– | –"
    return f"{metrics['psnr']:.2f} | {metrics['ssim']:.3f}"


def _delta_e(metrics: dict | None) -> str:
    value = (metrics or {}).get("delta_e2000")
    return "–" if value is None else f"{value:.2f}"


def _quality_table(summary: dict) -> list[str]:
    lines = ["| | relit PSNR | relit SSIM | albedo PSNR | albedo SSIM | albedo ΔE2000 |", "|---|---|---|---|---|---|"]
    for key, label in (("model", "model"), ("floor", "floor: input returned unchanged"),
                       ("ceiling", "ceiling: tokenizer encode→decode of the ground truth")):
        row = summary.get(key) or {}
        lines.append(f"| {label} | {_pair(row.get('relit'))} | {_pair(row.get('albedo'))} | "
                     f"{_delta_e(row.get('albedo'))} |")
    if "flicker" in ((summary.get("model") or {}).get("relit") or {}):   # clips: how steady, in levels of 255
        lines += ["", "| clips, ×255 | relit temporal error | relit flicker | albedo temporal error | albedo flicker |",
                  "|---|---|---|---|---|"]
        for key, label in (("model", "model"), ("floor", "floor: input returned unchanged")):
            row = summary.get(key) or {}
            cells = [f"{255 * (row.get(clip) or {}).get(name, float('nan')):.2f}"
                     for clip in ("relit", "albedo") for name in ("temporal", "flicker")]
            lines.append(f"| {label} | " + " | ".join(cells) + " |")
    return lines


def markdown(results: dict) -> str:
    """The whole report as Markdown."""
    model, data = results["model"], results["data"]
    test = results["test"]
    lines = [f"# Evaluation: {model['name']} on {data['root']}/{data['split']}", ""]
    if results.get("command"):
        lines += ["```", results["command"], "```", ""]
    lines += [f"Model `{model['source']}` ({'trained' if model['trained'] else 'random weights'}), "
              f"{model['steps']} {model['sampler']} steps, guidance {model['guidance']}, seed {model['seed']}, "
              f"{model['precision']} on {model['device']}; model size {model['size']} px, measured at "
              f"{data['measured_size'][1]}×{data['measured_size'][0]} "
              f"(dataset {data['native_size'][1]}×{data['native_size'][0]}), {data['frames']} frames per item; "
              f"{results['seconds']:.0f} s in all.", "", PROTOCOL, "",
              f"## {data['split'].capitalize()} split ({test['items']} items, "
              f"{test['seconds_per_item']:.1f} s per item)", ""]
    lines += _quality_table(test)
    if test.get("margin") is not None:
        lines += ["", f"**Probe-following margin: {test['margin']:+.2f} dB** (PSNR against the target's "
                  "own probe minus against the same scene under the other probe, the input relit under "
                  "both; ≈ 0 for a model that ignores the light)."]
    train = results["train"]
    lines += ["", f"## Train-set reproduction ({train['items']} train items)", ""]
    lines += _quality_table(train) if train["items"] else [f"Not measured: {str(train.get('note')).rstrip('.')}."]
    if results.get("steps"):
        lines += ["", "## Steps vs quality (test items)", "",
                  "| steps | relit PSNR | relit SSIM | albedo PSNR | albedo SSIM | albedo ΔE2000 | s / item |",
                  "|---|---|---|---|---|---|---|"]
        lines += [f"| {r['steps']} | {_pair(r['relit'])} | {_pair(r['albedo'])} | {_delta_e(r['albedo'])} | "
                  f"{r['seconds_per_item']:.1f} |" for r in results["steps"]]
    sigma = results.get("sigma", {})
    if sigma.get("test", {}).get("rows"):
        train_rows = sigma.get("train", {}).get("rows") or []
        lines += ["", f"## Denoiser error per σ ({sigma['test']['items']} test, "
                      f"{sigma.get('train', {}).get('items', 0)} train items, first chunk, "
                      f"{sigma['test']['steps']}-step schedule)", "",
                  "One denoiser call on the clean latents noised to σ, decoded; protocol PSNR of its x0 "
                  "(relit, albedo) and the relit latent MSE; 'no light' zeroes the lighting.", "",
                  "| σ | test relit PSNR | no light | train relit PSNR | no light | test albedo PSNR | "
                  "train albedo PSNR | test relit latent MSE | no light | train relit latent MSE |",
                  "|---|---|---|---|---|---|---|---|---|---|"]
        for i, row in enumerate(sigma["test"]["rows"]):
            tr = train_rows[i] if i < len(train_rows) else None

            def f(r, key, fmt="{:.2f}"):
                return fmt.format(r[key]) if r is not None else "–"
            lines.append(f"| {row['sigma']:.3g} | {f(row, 'relit_psnr')} | {f(row, 'relit_psnr_no_light')} | "
                         f"{f(tr, 'relit_psnr')} | {f(tr, 'relit_psnr_no_light')} | {f(row, 'albedo_psnr')} | "
                         f"{f(tr, 'albedo_psnr')} | {f(row, 'relit_latent_mse', '{:.4f}')} | "
                         f"{f(row, 'relit_latent_mse_no_light', '{:.4f}')} | {f(tr, 'relit_latent_mse', '{:.4f}')} |")
    full = results.get("full_resolution")
    if full:
        lines += ["", f"## Full-resolution output ({full['size']} px long side, {full['items']} items)", "",
                  f"The item at {full['size']} px stands for the user's photo; the model sees it at "
                  f"{model['size']} px. Oracle: the ground truth shrunk to the model's size and brought back up.", "",
                  "| | relit PSNR | relit SSIM | albedo PSNR | albedo SSIM |", "|---|---|---|---|---|",
                  f"| floor: input unchanged | {_pair(full['floor']['relit'])} | {_pair(full['floor']['albedo'])} |"]
        for source in ("model", "oracle"):
            for method, label in (("plain", "plain resize"), ("guided", "guided ratio upsampling")):
                lines.append(f"| {source}, {label} | {_pair(full[source]['relit'][method])} | "
                             f"{_pair(full[source]['albedo'][method])} |")
    follow = results.get("light_follow")
    if follow:
        s = follow["summary"]

        def g(key):
            return "–" if s[key] is None else f"{s[key]:.3f}"

        lines += ["", f"## Following a turning light ({follow['scenes']} held-out scenes rendered here)", "",
                  f"Each scene's input (under its own probe) relit under {follow['probe']} at world yaws "
                  f"{', '.join(f'{y:g}°' for y in follow['yaws'])}, against Mitsuba renders ({follow['size']} px, "
                  f"{follow['spp']} spp); every pair of yaws: the correlation of the result's log-luminance change "
                  "with the truth's (follow; its detail: less a σ 3 px blur), the slope of one on the other (reach), "
                  "the share of pixels whose light changes 1.5× or more that change the same way (agreement), and "
                  "how much of the input's shading the albedo keeps (1: all, the input copied; 0: none). Ceilings: "
                  "the truth against a second render with other noise (relight_core/evaluation/light_follow.py).", "",
                  "| | follow | follow, detail | reach | shadow agreement | albedo shading |", "|---|---|---|---|---|---|",
                  f"| model | {g('follow')} | {g('follow_detail')} | {g('reach')} | {g('shadow_agreement')} | "
                  f"{g('albedo_shading')} |",
                  f"| ceiling: the truth rendered again (reach, agreement, shading: ideal) | {g('follow_ceiling')} | "
                  f"{g('follow_detail_ceiling')} | 1 | 1 | 0 |",
                  "| input copied | 0 | 0 | 0 | – | 1 |"]
    lines += ["", "## Per item", "", "| item | relit PSNR | floor | ceiling | margin | albedo PSNR | floor | ceiling "
              "| albedo ΔE2000 |", "|---|---|---|---|---|---|---|---|---|"]
    for r, split in [(r, "") for r in test["per_item"]] + [(r, " (train)") for r in train.get("per_item") or []]:
        margin = f"{r['margin']:+.2f}" if "margin" in r else "–"
        lines.append(f"| {r['name']}{split} | {r['model']['relit']['psnr']:.2f} | {r['floor']['relit']['psnr']:.2f} | "
                     f"{r['ceiling']['relit']['psnr']:.2f} | {margin} | {r['model']['albedo']['psnr']:.2f} | "
                     f"{r['floor']['albedo']['psnr']:.2f} | {r['ceiling']['albedo']['psnr']:.2f} | "
                     f"{_delta_e(r['model']['albedo'])} |")
    grids = ["`grids/test_*.png`"] + (["`grids/train_*.png`"] if train["items"] else []) + \
        (["full resolution (input | target | plain | guided): `grids/full_*.png`"] if full else [])
    lines += ["", "Grids (input | target | relit | albedo target | albedo; rows: first, middle, last frame): "
              + ", ".join(grids) + "."]
    return "\n".join(lines) + "\n"
