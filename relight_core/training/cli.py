"""The training subcommands: `train-tokenizer` and `train` (DiT + export)."""

from __future__ import annotations

import argparse
import json
import os
import shlex
import sys
from pathlib import Path

from relight_core.data.cli import positive_int
from relight_core.errors import InputError


def _common(p: argparse.ArgumentParser) -> None:
    p.add_argument("--data", required=True, type=Path, help="dataset root written by render-data (train/, test/)")
    # --run-dir: torchrun's own parser takes --run for its --run-path (pytorch/pytorch#120601)
    p.add_argument("--run", "--run-dir", dest="run", required=True, type=Path,
                   help="run folder (log.jsonl, ckpt/); an existing run resumes; spell it --run-dir under torchrun")
    p.add_argument("--steps", type=positive_int, default=100000, help="stop after this many steps")
    p.add_argument("--minutes", type=float, default=None, help="stop after this much wall time")
    p.add_argument("--lr", type=float, default=2e-4, help="peak learning rate")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads (default: all cores)")
    p.add_argument("--checkpoint-minutes", type=float, default=5.0, help="checkpoint cadence")
    p.add_argument("--precision", choices=("auto", "fp32", "bf16"), default="auto",
                   help="compute precision; auto: bf16 autocast where this CPU runs it faster than fp32, else fp32")


def add_training_commands(subparsers) -> None:
    """Register `train-tokenizer` and `train` on an argparse subparsers object (sets `func`)."""
    p = subparsers.add_parser("train-tokenizer", help="train the small causal video tokenizer on a dataset")
    _common(p)
    p.add_argument("--preset", default="small", help="tokenizer preset (small, tiny)")
    p.add_argument("--crop", type=positive_int, default=64, help="random crop side in pixels")
    p.add_argument("--clip-batch", type=positive_int, default=4, help="clips per video step")
    p.add_argument("--image-batch", type=positive_int, default=16, help="images per image step")
    p.set_defaults(func=_train_tokenizer)

    p = subparsers.add_parser("train", help="train the joint relighting DiT on a trained tokenizer and export it")
    _common(p)
    p.add_argument("--tokenizer", required=True, type=Path, help="tokenizer weights from train-tokenizer")
    p.add_argument("--tokenizer-preset", default="small")
    p.add_argument("--preset", default="small", help="model preset the DiT comes from (small, tiny)")
    p.add_argument("--video-batch", type=positive_int, default=4)
    p.add_argument("--image-batch", type=positive_int, default=8)
    p.add_argument("--weight-decay", type=float, default=0.01)
    p.add_argument("--ema-decay", type=float, default=0.999, help="EMA decay (the EMA is what gets exported)")
    p.add_argument("--warmup", type=int, default=200, help="linear learning-rate warm-up steps")
    p.add_argument("--val-every", type=positive_int, default=250)
    p.add_argument("--log-every", type=positive_int, default=10, help="write a log line every this many steps")
    p.add_argument("--cache", type=Path, default=Path("cache/latents"), help="latent cache folder")
    p.add_argument("--export", type=Path, default=None, help="write the EMA model folder here at the end")
    p.add_argument("--device", choices=("cpu", "cuda"), default="cpu",
                   help="where the DiT trains; under torchrun, cuda gives each process the GPU of its local rank")
    p.set_defaults(func=_train)


def _setup(args) -> None:
    import torch

    if args.threads is not None:
        torch.set_num_threads(args.threads)
    if not (args.data / "train").is_dir():
        raise InputError(f"{args.data} has no train/ split; render one with "
                         f"`python -m relight_core render-data --out {args.data} --split train`.")


def _train_tokenizer(args) -> int:
    from relight_core.tokenizer import TOKENIZER_PRESETS
    from relight_core.training.autoencoder import TokenizerTrainConfig, train_tokenizer

    _setup(args)
    if args.preset not in TOKENIZER_PRESETS:
        raise InputError(f"Unknown tokenizer preset {args.preset!r}; use one of {sorted(TOKENIZER_PRESETS)}.")
    config = TokenizerTrainConfig(data=args.data, run=args.run, preset=args.preset, steps=args.steps,
                                  minutes=args.minutes, clip_batch=args.clip_batch, image_batch=args.image_batch,
                                  crop=args.crop, lr=args.lr, checkpoint_minutes=args.checkpoint_minutes,
                                  seed=args.seed, precision=args.precision)
    print(train_tokenizer(config))
    return 0


def _train(args) -> int:
    from relight_core.checkpoint import MODEL_PRESETS
    from relight_core.devices import resolve_device
    from relight_core.training import distributed
    from relight_core.training.joint import DiTTrainConfig, train_dit

    _setup(args)
    device = resolve_device(args.device)  # one sentence when --device cuda finds no GPU
    distributed.check_split(distributed.world_size(), video_batch=args.video_batch, image_batch=args.image_batch)
    if args.preset not in MODEL_PRESETS or MODEL_PRESETS[args.preset].tokenizer.get("type") != "causal-ae":
        raise InputError(f"Preset {args.preset!r} cannot be trained here; use 'small' or 'tiny'.")
    if not args.tokenizer.is_file():
        raise InputError(f"Tokenizer weights {args.tokenizer} do not exist; run train-tokenizer first "
                         "and pass its <run>/ckpt/tokenizer.safetensors.")
    config = DiTTrainConfig(data=args.data, run=args.run, tokenizer=args.tokenizer,
                            tokenizer_preset=args.tokenizer_preset, preset=args.preset, steps=args.steps,
                            minutes=args.minutes, video_batch=args.video_batch, image_batch=args.image_batch,
                            lr=args.lr, weight_decay=args.weight_decay, ema_decay=args.ema_decay,
                            warmup=args.warmup, val_every=args.val_every, log_every=args.log_every,
                            checkpoint_minutes=args.checkpoint_minutes, seed=args.seed, cache=args.cache,
                            export=args.export, precision=args.precision)
    launcher = (f"torchrun --nproc_per_node {os.environ.get('LOCAL_WORLD_SIZE', distributed.world_size())} -m"
                if distributed.launched() else "python -m")
    command = f"{launcher} relight_core " + " ".join(shlex.quote(a) for a in sys.argv[1:])
    ranks = distributed.join(device.type) if distributed.launched() else distributed.Ranks(device=device)
    try:
        summary = train_dit(config, command=command, ranks=ranks)
        distributed.barrier(ranks)   # the others wait while rank 0 writes the checkpoint and export
    finally:
        distributed.leave(ranks)
    if ranks.main:
        print(json.dumps(summary, indent=1))
    return 0
