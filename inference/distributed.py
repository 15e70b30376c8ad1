"""DDP plumbing of training (torchrun rank, its device, all-reduce, barrier), out of the loop."""

from __future__ import annotations

import os
from dataclasses import dataclass

import torch


@dataclass
class Dist:
    """This process's place in a ``torchrun`` launch (rank 0 of 1 when not distributed)."""

    rank: int = 0
    world: int = 1
    local_rank: int = 0

    @property
    def main(self) -> bool:
        return self.rank == 0


def init_distributed(device_kind: str) -> Dist:
    """Join the process group when ``WORLD_SIZE`` > 1: nccl on CUDA, gloo otherwise."""
    world = int(os.environ.get("WORLD_SIZE", "1"))
    if world <= 1:
        return Dist()
    import torch.distributed as dist

    if not dist.is_initialized():
        dist.init_process_group(backend="nccl" if device_kind == "cuda" else "gloo")
    return Dist(dist.get_rank(), dist.get_world_size(), int(os.environ.get("LOCAL_RANK", "0")))


def resolve_device(name: str, d: Dist) -> torch.device:
    """``"auto"`` is CUDA when available, else CPU; CUDA picks this rank's local GPU."""
    if name == "auto":
        name = "cuda" if torch.cuda.is_available() else "cpu"
    if name == "cuda":
        return torch.device("cuda", d.local_rank)
    return torch.device(name)


def all_reduce_sum(values: list[float], d: Dist, device: torch.device) -> list[float]:
    """Sum ``values`` over all ranks (float64), so every rank takes the same decisions."""
    if d.world == 1:
        return values
    import torch.distributed as dist

    t = torch.tensor(values, dtype=torch.float64, device=device)
    dist.all_reduce(t)
    return t.tolist()


def barrier(d: Dist) -> None:
    """Wait for every rank (no-op when not distributed)."""
    if d.world > 1:
        import torch.distributed as dist

        dist.barrier()
