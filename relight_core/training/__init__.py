"""Training: the small tokenizer, then the joint relighting DiT (UniRelight recipe), then export.

Modules: `loop` (per-step RNG, EMA, checkpoints, JSONL log), `autoencoder` (tokenizer training),
`latents` (latent cache of a dataset split), `recipe` (conditioning modes, lighting dropout, EDM
loss), `joint` (DiT training, validation, export), `distributed` (data-parallel `train` under
torchrun), `cli` (`train-tokenizer`, `train`).
Only the CLI hook is imported here, so registering the subcommands stays cheap.
"""

from relight_core.training.cli import add_training_commands

__all__ = ["add_training_commands"]
