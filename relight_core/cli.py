"""Command line: `python -m relight_core relight|augment|albedo|render|bench|...`.

Every user error ends the same way: one sentence on stderr and exit code 2, with nothing written
into the output folder (outputs are staged in a hidden folder and moved in at the very end).
"""

from __future__ import annotations

import argparse
import os
import shutil
import sys
import tempfile
from pathlib import Path

from relight_core.arguments import (MAX_INTENSITY, MAX_ROTATION_DEG, MAX_SEED, OneLineParser, finite_float,
                                    int_range, seed, terminate_as_interrupt)
from relight_core.data.cli import add_data_commands, positive_int
from relight_core.errors import InputError
from relight_core.evaluation.cli import add_evaluation_commands
from relight_core.training.cli import add_training_commands

EXIT_USER_ERROR = 2


MAX_SEEDS = 256


def _parse_seeds(text: str) -> list[int]:
    """"0-7" → [0..7]; "1,5,9" → [1,5,9]; "3" → [3]. Seeds are 0 … 2⁶³−1, at most 256 of them."""
    seeds: list[int] = []
    try:
        for part in text.split(","):
            part = part.strip()
            if "-" in part[1:]:
                lo_text, hi_text = part.rsplit("-", 1)
                lo, hi = int(lo_text), int(hi_text)
                if hi < lo:
                    raise argparse.ArgumentTypeError(
                        f"the seed range '{part}' is reversed; write the smaller seed first, e.g. {hi}-{lo}.")
                if hi - lo + 1 > MAX_SEEDS - len(seeds):  # checked before the range is expanded
                    raise argparse.ArgumentTypeError(
                        f"'{text}' names more than {MAX_SEEDS} seeds; give between 1 and {MAX_SEEDS}, e.g. 0-7.")
                seeds.extend(range(lo, hi + 1))
            else:
                seeds.append(int(part))
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a seed list; write e.g. 0-7 or 1,5,9.") from None
    if not seeds or len(seeds) > MAX_SEEDS:
        raise argparse.ArgumentTypeError(f"Give between 1 and {MAX_SEEDS} seeds, e.g. 0-7.")
    outside = [s for s in seeds if not 0 <= s <= MAX_SEED]
    if outside:
        raise argparse.ArgumentTypeError(f"the seed {outside[0]} is out of range; seeds are whole numbers "
                                         f"from 0 to {MAX_SEED}.")
    return seeds


def _frame_range(text: str) -> tuple[int, int | None]:
    """"START:END" (END exclusive, optional) → (start, end)."""
    try:
        start, _, end = text.partition(":")
        return int(start or 0), (int(end) if end else None)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a frame range; write e.g. 0:57.") from None


def _sampler(text: str) -> str:
    """--sampler: one of the samplers in relight_core.diffusion."""
    from relight_core.diffusion import SAMPLERS

    if text not in SAMPLERS:
        raise argparse.ArgumentTypeError(f"'{text}' is not a sampler; choose one of {', '.join(SAMPLERS)}.")
    return text


def _precision(text: str) -> str:
    """--precision: one of auto, fp32, bf16, fp16."""
    from relight_core.precision import PRECISIONS

    if text not in PRECISIONS:
        raise argparse.ArgumentTypeError(f"'{text}' is not a precision; choose one of {', '.join(PRECISIONS)}.")
    return text


def _add_precision_arg(p: argparse.ArgumentParser, default: str | None) -> None:
    p.add_argument("--precision", type=_precision, default=default, metavar="{auto,fp32,bf16,fp16}",
                   help="compute precision; auto: bf16 where this machine runs it faster than fp32, else fp32 "
                        "(default: the model's, normally auto); fp16 only on a CUDA GPU")


def _add_model_args(p: argparse.ArgumentParser) -> None:
    p.add_argument("--model", default="default",
                   help="'default' (shipped small model), a preset (tiny, small, unirelight-7b) or a model folder")
    p.add_argument("--steps", type=int_range(1, 1000, "number of steps"), default=None,
                   help="sampling steps, 1 to 1000 (default: the model's)")
    p.add_argument("--sampler", type=_sampler, default=None, help="res2ab (default), euler or heun")
    p.add_argument("--guidance", type=finite_float(0.0, 100.0, what="guidance"), default=0.0,
                   help="classifier-free guidance (0 = off, one pass)")
    p.add_argument("--size", type=positive_int, default=None, help="working resolution: long side in pixels")
    p.add_argument("--frames", type=_frame_range, default=(0, None), metavar="START:END",
                   help="frame range of a video (END exclusive)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    _add_precision_arg(p, None)
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--raw", action="store_true",
                   help="write the model-size output as it is (default: guided upsampling to the input's resolution)")


def _add_probe_args(p: argparse.ArgumentParser, required: bool) -> None:
    p.add_argument("--probe", required=required, type=Path, help="HDR environment map (.exr or .hdr)")
    p.add_argument("--rotation", type=finite_float(-MAX_ROTATION_DEG, MAX_ROTATION_DEG, what="rotation"),
                   default=None, help="yaw of the probe in degrees")
    p.add_argument("--rotate-light", action="store_true", help="sweep the probe's yaw through 360° over the clip")
    p.add_argument("--intensity", type=finite_float(0.0, MAX_INTENSITY, low_open=True, what="intensity"),
                   default=1.0, help="multiplier on the probe's radiance (> 0)")
    p.add_argument("--temperature", type=float, default=None, metavar="KELVIN",
                   help="the light's colour temperature: 6500 is neutral (the default), lower warmer, higher "
                        "cooler (1700 to 25000)")
    p.add_argument("--camera-pitch", type=float, default=0.0, metavar="DEGREES",
                   help="how far the camera looks up (+) or down (-) from level, -90 to 90")
    p.add_argument("--camera-roll", type=float, default=0.0, metavar="DEGREES",
                   help="how far the camera is turned counter-clockwise (+) about its view, -180 to 180")


def build_parser() -> argparse.ArgumentParser:
    parser = OneLineParser(prog="python -m relight_core",
                                     description="UniRelight Studio: relight images and videos.")
    sub = parser.add_subparsers(dest="command", required=True)

    p = sub.add_parser("relight", help="relight an image or video under an HDR probe")
    p.add_argument("input", type=Path)
    _add_probe_args(p, required=True)
    p.add_argument("--seed", type=seed, default=0, help=f"random seed, 0 to {MAX_SEED}")
    _add_model_args(p)

    p = sub.add_parser("augment", help="random illuminations, one result per seed (no probe)")
    p.add_argument("input", type=Path)
    p.add_argument("--seeds", type=_parse_seeds, default=_parse_seeds("0-7"))
    _add_model_args(p)

    p = sub.add_parser("albedo", help="estimate the albedo of an image or video (inverse rendering)")
    p.add_argument("input", type=Path)
    p.add_argument("--seed", type=seed, default=0, help=f"random seed, 0 to {MAX_SEED}")
    _add_model_args(p)

    p = sub.add_parser("render", help="render a given albedo under an HDR probe (forward rendering)")
    p.add_argument("input", type=Path, help="albedo image or video")
    _add_probe_args(p, required=True)
    p.add_argument("--seed", type=seed, default=0, help=f"random seed, 0 to {MAX_SEED}")
    _add_model_args(p)

    p = sub.add_parser("bench", help="measure DiT throughput, sampler cost and memory on this machine")
    p.add_argument("--quick", action="store_true", help="tiny preset only, fewer repeats")
    _add_precision_arg(p, "auto")
    p.add_argument("--out", type=Path, default=None, help="also write the numbers as JSON here")

    p = sub.add_parser("import-released", help="make a model folder from the released UniRelight files")
    p.add_argument("--checkpoint", required=True, type=Path, help="UniRelight/model.pt")
    p.add_argument("--tokenizer", required=True, type=Path, help="the Cosmos-Tokenize1-CV8x8x8-720p folder")
    p.add_argument("--out", required=True, type=Path, help="model folder to write (then use --model OUT)")

    add_data_commands(sub)
    add_training_commands(sub)
    add_evaluation_commands(sub)
    return parser


def main(argv: list[str] | None = None) -> int:
    with terminate_as_interrupt():  # SIGTERM (kill, timeout) cleans up like Ctrl+C
        return _main(argv)


def _main(argv: list[str] | None) -> int:
    args = build_parser().parse_args(argv)
    try:
        if args.command == "bench":
            from relight_core.bench import run_bench
            run_bench(quick=args.quick, out=args.out, precision=args.precision)
            return 0
        if args.command == "import-released":
            from relight_core.released import import_released
            print(import_released(args.checkpoint, args.tokenizer, args.out))
            return 0
        if args.command in ("relight", "augment", "albedo", "render"):
            return _run_media_command(args)
        return args.func(args)
    except InputError as exc:
        print(f"error: {exc}", file=sys.stderr)
        return EXIT_USER_ERROR
    except OSError as exc:  # an output folder that cannot be made or written, a full disk
        where = f" ({exc.filename})" if exc.filename else ""
        print(f"error: {exc.strerror or exc}{where}; choose another output folder or free some space.",
              file=sys.stderr)
        return EXIT_USER_ERROR
    except KeyboardInterrupt as exc:
        print("stopped.", file=sys.stderr)
        return getattr(exc, "exit_code", 130)


def _run_media_command(args) -> int:
    from tqdm import tqdm

    from relight_core import lighting, media
    from relight_core.pipeline import ChunkDone, Finished, Progress, Relighter, RelightRequest
    from relight_core.upsample import guided_ratio_upsample

    start, end = args.frames
    source = media.load_media(args.input, start=start, end=end)
    probe = None
    if getattr(args, "probe", None) is not None:
        probe = lighting.load_probe(args.probe, intensity=args.intensity)
    relighter = Relighter.load(args.model, device=args.device, precision=args.precision)
    size = args.size or relighter.spec.size
    # Refuse a working size this machine cannot hold before allocating anything at that size.
    relighter.check_memory(source.frames.shape[0], *media.target_size(*source.frames.shape[1:3], size,
                                                                      relighter.frame_multiple),
                           guidance=args.guidance > 0, hint="pass a smaller --size")
    if not relighter.spec.trained:
        print(f"note: model '{relighter.spec.name}' has random weights; results will be noise.",
              file=sys.stderr)
    frames = media.resize_frames(source.frames, size, multiple=relighter.frame_multiple)
    base = dict(fps=source.fps, audio_path=source.audio_path, audio_start=source.audio_start, steps=args.steps,
                sampler=args.sampler, guidance=args.guidance)
    if getattr(args, "rotation", None) is not None:
        base["rotation"] = args.rotation
    if getattr(args, "rotate_light", False):
        base["rotate_light"] = True
    if getattr(args, "temperature", None) is not None:
        base["temperature"] = lighting.check_temperature(args.temperature)  # out of range: one sentence
    if getattr(args, "camera_pitch", 0.0) or getattr(args, "camera_roll", 0.0):
        lighting.camera_rotation(args.camera_pitch, args.camera_roll)  # out of range: one sentence
        base["camera_pitch"], base["camera_roll"] = args.camera_pitch, args.camera_roll

    if args.command == "relight":
        jobs = [("", RelightRequest(frames, mode="relight", probe=probe, seed=args.seed, **base))]
    elif args.command == "render":
        jobs = [("", RelightRequest(frames, mode="render", probe=probe, albedo=frames, seed=args.seed, **base))]
    elif args.command == "albedo":
        jobs = [("", RelightRequest(frames, mode="albedo", seed=args.seed, **base))]
    else:
        jobs = [(f"seed{seed:04d}_", RelightRequest(frames, mode="random", seed=seed, **base))
                for seed in args.seeds]

    args.out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".partial-", dir=args.out))
    try:
        written = []
        for prefix, request in jobs:
            result = None
            with tqdm(desc=f"{args.command} {prefix.rstrip('_')}".strip(), unit="step", file=sys.stderr,
                      disable=None) as bar:
                for event in relighter.run(request):
                    if isinstance(event, Progress):
                        bar.total = event.total_steps * event.num_chunks
                        bar.update(1)
                    elif isinstance(event, ChunkDone):
                        bar.set_postfix(chunk=f"{event.chunk + 1}/{event.num_chunks}")
                    elif isinstance(event, Finished):
                        result = event.result
            outputs = {"albedo": result.albedo} if args.command == "albedo" else {"relit": result.relit,
                                                                                   "albedo": result.albedo}
            if args.command == "augment":
                outputs = {"relit": result.relit}
            if not args.raw:  # the model's size → the input's, by guided ratio transfer (upsample.py)
                outputs = {name: guided_ratio_upsample(source.frames, frames, out_frames)
                           for name, out_frames in outputs.items()}
            for name, out_frames in outputs.items():
                if source.is_video:
                    path = staging / f"{prefix}{name}.mp4"
                    media.save_video(path, out_frames, source.fps, audio_from=source.audio_path,
                                     audio_start=source.audio_start)
                else:
                    path = staging / f"{prefix}{name}.png"
                    media.save_image(path, out_frames[0])
                written.append(path)
        for path in written:
            os.replace(path, args.out / path.name)
            print(args.out / path.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return 0
