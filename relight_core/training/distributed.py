"""Data-parallel training under torchrun (DDP): the process group and the split of each global batch.

`torchrun --nproc_per_node N -m relight_core train ...` starts N processes; each finds its rank in
the environment torchrun sets, joins one process group (gloo on CPUs, NCCL with one GPU per local
rank) and trains a DistributedDataParallel copy of the DiT. The run is the run one process makes
with the same global batch, whatever N:

* every rank draws the whole global batch from `step_generator(seed, step)` — items, image frames,
  conditioning modes, lighting dropout, σ, noise and the condition-clip noise — exactly as one
  process does, and computes the network on its own rows only (`rank_rows`): no random number
  depends on N (`joint.train_step_rows`);
* a rank's loss is its rows' mean weighted by its share of the batch, times N (DDP averages the
  gradients), so the averaged gradient is that of the global batch's mean loss;
* each rank encodes its shard of the scenes into the shared latent cache (`build_latent_set(...,
  shard=)`), then all read the whole cache;
* rank 0 alone writes the log, the checkpoints and the export; checkpoints hold nothing that
  depends on N, so a run resumes under any N (one process included).

Without torchrun none of this runs and `train` is the single-process trainer it always was.
"""

from __future__ import annotations

import datetime
import gc
import os
from dataclasses import dataclass, field

import torch
import torch.distributed as dist

from relight_core.errors import InputError

# Encoding a large dataset's latents happens between two barriers: allow it hours, not minutes.
TIMEOUT = datetime.timedelta(hours=2)


@dataclass(frozen=True)
class Ranks:
    """Where this process sits in a training run: rank 0 of 1 on the CPU when not under torchrun."""

    rank: int = 0
    world: int = 1
    device: torch.device = field(default_factory=lambda: torch.device("cpu"))
    group: bool = False                  # a torch.distributed process group is joined (DDP)

    @property
    def main(self) -> bool:
        """Whether this rank writes the log, the checkpoints and the export."""
        return self.rank == 0


def launched() -> bool:
    """Whether torchrun (`torch.distributed.run`) started this process."""
    return dist.is_torchelastic_launched()


def world_size() -> int:
    """N of `--nproc_per_node N` (summed over nodes) under torchrun, else 1."""
    return int(os.environ.get("WORLD_SIZE", "1")) if launched() else 1


def check_split(world: int, **batches: int) -> None:
    """InputError unless every global batch gives each of `world` ranks at least one row."""
    for name, size in batches.items():
        if size < world:
            flag = name.replace("_", "-")
            raise InputError(f"{world} processes cannot split a {name.replace('_', ' ')} of {size}; "
                             f"pass --{flag} {world} or more, or start fewer processes.")


def join(device: str = "cpu") -> Ranks:
    """Join torchrun's process group: NCCL with GPU `LOCAL_RANK` when `device` is cuda, else gloo."""
    local = int(os.environ["LOCAL_RANK"])
    if torch.device(device).type == "cuda":
        torch.cuda.set_device(local)
        here, backend = torch.device("cuda", local), "nccl"
    else:
        here, backend = torch.device("cpu"), "gloo"
    dist.init_process_group(backend, timeout=TIMEOUT)
    return Ranks(dist.get_rank(), dist.get_world_size(), here, group=True)


def leave(ranks: Ranks) -> None:
    """Leave the process group `join` made (nothing for a single process).

    The DDP wrapper's reducer holds the group; collecting it first lets `destroy_process_group`
    really close gloo's threads. Left to the interpreter's exit instead, a rank sometimes died with
    SIGABRT ("terminate called without an active exception") after its last step (1 run in 6-7).
    """
    if ranks.group and dist.is_initialized():
        gc.collect()
        dist.destroy_process_group()


def rank_rows(batch_size: int, rank: int, world: int) -> slice:
    """Rank `rank`'s contiguous rows of a global batch; shares differ by at most one row."""
    base, extra = divmod(batch_size, world)
    start = rank * base + min(rank, extra)
    return slice(start, start + base + (1 if rank < extra else 0))


def barrier(ranks: Ranks) -> None:
    """Wait for every rank (nothing for a single process)."""
    if ranks.group:
        dist.barrier()


def global_sum(value: torch.Tensor, ranks: Ranks) -> torch.Tensor:
    """Sum of a scalar over the ranks (the value itself for a single process)."""
    if not ranks.group:
        return value
    total = value.detach().to(ranks.device, torch.float64).reshape(1).clone()
    dist.all_reduce(total)
    return total[0]


def agree(flag: bool, ranks: Ranks) -> bool:
    """Rank 0's `flag` on every rank (wall-clock limits must stop every rank at the same step)."""
    if not ranks.group:
        return flag
    value = torch.tensor([int(flag)], device=ranks.device)
    dist.broadcast(value, src=0)
    return bool(value.item())
