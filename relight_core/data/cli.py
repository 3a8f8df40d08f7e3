"""The data engine's subcommands: `render-data` (synthetic scenes) and `autolabel` (real videos)."""

from __future__ import annotations

from pathlib import Path

from relight_core.arguments import finite_float, int_at_least
from relight_core.errors import InputError


positive_int = int_at_least(1)  # argparse type: a whole number ≥ 1
RAY_ADDRESS_HELP = "a running Ray cluster (see 'ray start --head' and docs/SCALE.md); default: a local Ray instance"


def add_data_commands(subparsers) -> None:
    """Register `render-data` and `autolabel` on an argparse subparsers object (sets `func`)."""
    p = subparsers.add_parser("render-data", help="path-trace synthetic multi-illumination training data")
    p.add_argument("--out", required=True, type=Path, help="dataset folder (scenes go to OUT/SPLIT/)")
    p.add_argument("--scenes", type=positive_int, default=100, help="number of scenes")
    p.add_argument("--frames", type=positive_int, default=9, help="frames per scene; the tokenizer takes 1 + 8k (1 = images, 9, 17, ...)")
    p.add_argument("--size", type=positive_int, default=128, help="frame side in pixels")
    p.add_argument("--spp", type=positive_int, default=64, help="samples per pixel (rounded up to a square, k×k stratified)")
    p.add_argument("--seed", type=int, default=0,
                   help="dataset seed: same seed, same scenes (on the CPU the same files, byte for byte)")
    p.add_argument("--workers", type=positive_int, default=None,
                   help="scenes rendered at once, one CPU each (default: one per CPU of this machine, or of the "
                        "cluster with --ray-address; with --device cuda, as many as --gpus-per-worker fits on the "
                        "GPUs); 1 without --ray-address renders in this process, without Ray")
    p.add_argument("--ray-address", default=None, metavar="HOST:PORT", help=RAY_ADDRESS_HELP)
    p.add_argument("--split", choices=("train", "test"), default="train",
                   help="test uses held-out probes, meshes and textures")
    p.add_argument("--device", choices=("cpu", "cuda", "auto"), default="cpu",
                   help="cpu: Mitsuba's llvm_ad_rgb (the same bytes on every run; default); cuda: its cuda_ad_rgb on "
                        "an NVIDIA GPU (the same scenes, images equal to within the render noise); auto: cuda where "
                        "it renders, else cpu")
    p.add_argument("--gpus-per-worker", type=finite_float(0.0, 64.0, low_open=True, what="GPUs per worker"),
                   default=0.25, help="with --device cuda: each scene's share of a GPU (default 0.25: 4 at once)")
    p.add_argument("--minutes", type=finite_float(0.0, 1e6, low_open=True, what="minutes"), default=None,
                   help="start no scene after this many minutes; the same command renders the rest later")
    p.add_argument("--probes", choices=("classic", "extended"), default="classic",
                   help="probe library: classic (default; the scenes every earlier dataset of a seed has) or extended "
                        "(the train split also lit by the 11 HDRIs of envmaps/extra/; the test split is the same)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_render_data)

    p = subparsers.add_parser("autolabel", help="label real single-illumination videos with the model's albedo")
    p.add_argument("videos", type=Path, help="folder of videos (and/or images)")
    p.add_argument("--out", required=True, type=Path, help="dataset folder (samples go to OUT/SPLIT/)")
    p.add_argument("--split", default="real", help="split folder name")
    p.add_argument("--model", default="default", help="model to run in albedo mode")
    p.add_argument("--size", type=positive_int, default=None, help="working resolution (default: the model's)")
    p.add_argument("--max-frames", type=positive_int, default=None, help="cut each video to this many frames")
    p.add_argument("--steps", type=positive_int, default=None, help="sampling steps (default: the model's)")
    p.add_argument("--device", default=None,
                   help="cpu or cuda (default: GPU workers when the Ray cluster has GPUs, else CPU workers)")
    p.add_argument("--ray-address", default=None, metavar="HOST:PORT", help=RAY_ADDRESS_HELP)
    p.add_argument("--workers", type=positive_int, default=None,
                   help="workers, each holding one model (default: one per GPU, else one per --cpus-per-worker "
                        "CPUs); 1 without --ray-address labels in this process, without Ray")
    p.add_argument("--cpus-per-worker", type=positive_int, default=1,
                   help="CPUs each worker reserves; a CPU worker runs torch on as many threads (default: 1)")
    p.add_argument("--gpus-per-worker", type=finite_float(0.0, 64.0, low_open=True, what="GPUs per worker"),
                   default=1.0, help="GPUs each GPU worker reserves; a fraction shares one GPU (default: 1)")
    p.add_argument("--quiet", action="store_true", help="no progress bar")
    p.set_defaults(func=_autolabel)


def _render_data(args) -> int:
    from relight_core.batch.samples import report
    from relight_core.data.generate import RenderConfig, render_dataset

    if args.size % 16:
        raise InputError(f"--size {args.size} is not a multiple of 16; the tokenizer needs one (e.g. 128).")
    _check_address(args.ray_address)
    config = RenderConfig(out=args.out, scenes=args.scenes, frames=args.frames, size=args.size, spp=args.spp,
                          seed=args.seed, workers=args.workers, split=args.split, address=args.ray_address,
                          device=args.device, gpus_per_worker=args.gpus_per_worker, minutes=args.minutes,
                          probes=args.probes)
    return report(render_dataset(config, progress=not args.quiet), "scene")


def _autolabel(args) -> int:
    from relight_core.batch.samples import report
    from relight_core.data.autolabel import autolabel

    if not args.videos.is_dir():
        raise InputError(f"{args.videos} is not a folder; give the folder that holds the videos to label.")
    _check_address(args.ray_address)
    summary = autolabel(args.videos, args.out, split=args.split, model=args.model, size=args.size,
                        max_frames=args.max_frames, steps=args.steps, device=args.device, address=args.ray_address,
                        workers=args.workers, cpus_per_worker=args.cpus_per_worker,
                        gpus_per_worker=args.gpus_per_worker, progress=not args.quiet)
    return report(summary, "video")


def _check_address(address: str | None) -> None:
    """A cluster that is not there is one sentence before anything else starts."""
    if address:
        from relight_core.batch.engine import check_reachable

        check_reachable(address)
