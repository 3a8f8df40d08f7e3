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

from relight_core.arguments import (MAX_ENSEMBLE, MAX_INTENSITY, MAX_ROTATION_DEG, MAX_SEED, PRECISIONS, OneLineParser,
                                    finite_float, int_range, row_list, seed, seed_list, terminate_as_interrupt)
from relight_core.data.cli import add_data_commands, positive_int
from relight_core.errors import InputError
from relight_core.paths import check_path
from relight_core.streaming import stop_all
from relight_core.evaluation.cli import add_evaluation_commands
from relight_core.training.cli import add_training_commands

EXIT_USER_ERROR = 2


def _frame_range(text: str) -> tuple[int, int | None]:
    """"START:END" (END exclusive, optional) → (start, end)."""
    try:
        start, _, end = text.partition(":")
        start, end = int(start or 0), (int(end) if end else None)
    except ValueError:
        raise argparse.ArgumentTypeError(f"'{text}' is not a frame range; write e.g. 0:57.") from None
    if start < 0 or (end is not None and end <= start):
        raise argparse.ArgumentTypeError(f"the frame range '{text}' holds no frame; write START:END with "
                                         "0 ≤ START < END (END excluded), e.g. 0:57.")
    return start, end


def _sampler(text: str) -> str:
    """--sampler: one of the samplers in relight_core.diffusion."""
    from relight_core.diffusion import SAMPLERS

    if text not in SAMPLERS:
        raise argparse.ArgumentTypeError(f"'{text}' is not a sampler; choose one of {', '.join(SAMPLERS)}.")
    return text


def _mode(text: str) -> str:
    """--mode: one of the pipeline's modes."""
    from relight_core.pipeline import MODES

    if text not in MODES:
        raise argparse.ArgumentTypeError(f"'{text}' is not a mode; choose one of {', '.join(MODES)}.")
    return text


def _precision(text: str) -> str:
    """--precision: one of auto, fp32, bf16, fp16."""
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
    p.add_argument("--ensemble", type=int_range(1, MAX_ENSEMBLE, "ensemble"), default=None,
                   help="samples averaged into each result, every second one on the mirror image "
                        f"(1 to {MAX_ENSEMBLE}; default: the model's)")
    p.add_argument("--size", type=positive_int, default=None, help="working resolution: long side in pixels")
    p.add_argument("--frames", type=_frame_range, default=(0, None), metavar="START:END",
                   help="frame range of a video (END exclusive)")
    p.add_argument("--device", default=None, help="cpu or cuda (default: cuda when available)")
    _add_precision_arg(p, None)
    p.add_argument("--out", required=True, type=Path, help="output folder")
    p.add_argument("--raw", action="store_true",
                   help="write the model-size output as it is (default: guided upsampling to the input's resolution)")
    p.add_argument("--per-frame", action="store_true",
                   help="a video's frames as the model made them, without the model's filter along time "
                        "(default: a model with a temporal_filter steadies them)")


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
    p.add_argument("--tint", type=float, default=0.0, metavar="DUV",
                   help="green (+) or magenta (-) shift of the light's colour, -0.02 to 0.02 (0: none)")
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
    p.add_argument("--seeds", type=seed_list, default=seed_list("0-7"))
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

    p = sub.add_parser("batch", help="run a CSV manifest of images and videos on Ray (this machine or a cluster)")
    p.add_argument("manifest", type=Path, help="CSV with a header: input (required), mode, probe, rotation, "
                                               "intensity, seeds, steps, size; an empty cell takes the flag's value")
    p.add_argument("--mode", type=_mode, default="relight", help="relight (default), albedo, render or random")
    _add_probe_args(p, required=False)
    p.add_argument("--seeds", type=seed_list, default=None, help="one result per seed (default: 0; random: 0-7)")
    _add_model_args(p)
    p.add_argument("--ray-address", default=None, metavar="HOST:PORT",
                   help="a running Ray cluster (see 'ray start --head'); default: a local Ray instance")
    p.add_argument("--workers", type=positive_int, default=None,
                   help="workers, each holding one model (default: one per GPU, else one per --cpus-per-worker CPUs)")
    p.add_argument("--cpus-per-worker", type=positive_int, default=1,
                   help="CPUs each worker reserves; a CPU worker runs torch on as many threads (default: 1)")
    p.add_argument("--gpus-per-worker", type=finite_float(0.0, 64.0, low_open=True, what="GPUs per worker"),
                   default=1.0, help="GPUs each GPU worker reserves; a fraction shares one GPU (default: 1)")
    p.add_argument("--retry-failed", action="store_true", help="also run the rows that failed before")
    p.add_argument("--rows", type=row_list, default=None, metavar="LIST",
                   help="run exactly these rows (e.g. 3 or 1,4 or 2-5, counted from 1 under the header)")

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
        try:
            return _main(argv)
        finally:
            stop_all()  # no sampler thread may still be inside torch when the interpreter exits


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
        if args.command == "batch":
            return _run_batch_command(args)
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


def _media_job(args):
    """The flags of relight / augment / albedo / render (or batch's defaults) as a MediaJob (jobs.py)."""
    from relight_core.jobs import MediaJob

    mode = {"augment": "random", "batch": getattr(args, "mode", None)}.get(args.command, args.command)
    return MediaJob(mode=mode, input=getattr(args, "input", Path()),
                    probe=getattr(args, "probe", None), rotation=getattr(args, "rotation", None),
                    rotate_light=getattr(args, "rotate_light", False), intensity=getattr(args, "intensity", 1.0),
                    temperature=getattr(args, "temperature", None), tint=getattr(args, "tint", 0.0),
                    camera_pitch=getattr(args, "camera_pitch", 0.0), camera_roll=getattr(args, "camera_roll", 0.0),
                    seeds=tuple(getattr(args, "seeds", None) or (getattr(args, "seed", 0),)), steps=args.steps,
                    sampler=args.sampler, guidance=args.guidance, ensemble=args.ensemble, size=args.size, frames=args.frames, raw=args.raw,
                    per_frame=getattr(args, "per_frame", False))


def _run_media_command(args) -> int:
    check_path(args.input)  # a missing input is said at once, before the heavy imports
    from tqdm import tqdm

    from relight_core.jobs import load_inputs, plan_job, write_job
    from relight_core.pipeline import ChunkDone, Finished, Progress, Relighter

    job = _media_job(args)
    inputs = load_inputs(job)
    relighter = Relighter.load(args.model, device=args.device, precision=args.precision)
    plan = plan_job(job, relighter, inputs)
    if not relighter.spec.trained:
        print(f"note: model '{relighter.spec.name}' has random weights; results will be noise.",
              file=sys.stderr)

    def follow(prefix, events):
        with tqdm(desc=f"{args.command} {prefix.rstrip('_')}".strip(), unit="step", file=sys.stderr,
                  disable=None) as bar:
            for event in events:
                if isinstance(event, Progress):
                    bar.total = event.evaluations * event.num_chunks
                    bar.update(1)
                elif isinstance(event, ChunkDone):
                    bar.set_postfix(chunk=f"{event.chunk + 1}/{event.num_chunks}")
                elif isinstance(event, Finished):
                    return event.result
        raise InputError("The job was stopped before it finished.")

    args.out.mkdir(parents=True, exist_ok=True)
    staging = Path(tempfile.mkdtemp(prefix=".partial-", dir=args.out))
    try:
        written = write_job(job, relighter, inputs, plan, staging, follow)
        for path in written:
            os.replace(path, args.out / path.name)
            print(args.out / path.name)
    finally:
        shutil.rmtree(staging, ignore_errors=True)
    return 0


def _run_batch_command(args) -> int:
    import dataclasses

    from relight_core.batch import BatchOptions, run_batch

    template = _media_job(args)
    template = dataclasses.replace(template, probe=template.probe and template.probe.resolve())  # for workers
    options = BatchOptions(address=args.ray_address, workers=args.workers, cpus_per_worker=args.cpus_per_worker,
                           gpus_per_worker=args.gpus_per_worker, model=args.model, device=args.device,
                           precision=args.precision, retry_failed=args.retry_failed,
                           rows=frozenset(args.rows) if args.rows is not None else None)
    summary = run_batch(args.manifest, args.out, template, tuple(args.seeds) if args.seeds else None, options)
    print(summary.results)
    print(f"{summary.done} of {summary.rows} rows done, {summary.failed} failed.", file=sys.stderr)
    if summary.failed:
        print(f"error: {summary.failed} row{'s' * (summary.failed != 1)} failed; their reasons are in "
              f"{summary.results} (fix them, then run again with --retry-failed).", file=sys.stderr)
        return 1
    return 0
