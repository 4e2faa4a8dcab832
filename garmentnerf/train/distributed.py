"""Data-parallel training by hand over ``torch.distributed`` (see :mod:`garmentnerf.train.trainer`'s
"Devices and several processes"): every rank trains on its share, gradients are averaged after
every backward pass as DDP does (a training step is two calls, ``prepare_frame`` then ``render``,
not one ``forward``), and rank 0 alone writes files.
"""

from __future__ import annotations

import os

import torch
import torch.distributed as dist

__all__ = ["Distributed"]


class Distributed:
    """torch.distributed from the torchrun environment (a no-op for one process).

    Under ``torchrun`` (``WORLD_SIZE > 1``) the process group is initialised from the environment
    (NCCL on CUDA, gloo otherwise; each rank uses ``cuda:LOCAL_RANK``) unless it already is, and
    destroyed by :meth:`close` when this object made it.

    Attributes:
        world: number of processes (1 without torchrun).
        rank: this process's rank (0 is the one that writes files).
        local_rank: this process's rank on its machine (its CUDA device under torchrun).
    """

    def __init__(self, device: str):
        self.dist = dist
        self.world = int(os.environ.get("WORLD_SIZE", "1"))
        self.rank = int(os.environ.get("RANK", "0"))
        self.local_rank = int(os.environ.get("LOCAL_RANK", "0"))
        self.owned = False
        if self.world > 1:
            if not dist.is_initialized():
                backend = "nccl" if device.startswith("cuda") else "gloo"
                if device.startswith("cuda"):
                    torch.cuda.set_device(self.local_rank)
                dist.init_process_group(backend=backend)
                self.owned = True
            self.world, self.rank = dist.get_world_size(), dist.get_rank()

    @property
    def active(self) -> bool:
        return self.world > 1

    @property
    def main(self) -> bool:
        return self.rank == 0

    def barrier(self) -> None:
        if self.active:
            self.dist.barrier()

    def all_ok(self, ok: bool) -> bool:
        """True when ``ok`` on every rank (so all ranks raise together)."""
        if not self.active:
            return ok
        t = torch.tensor([0 if ok else 1], dtype=torch.int64)
        if self.dist.get_backend() == "nccl":
            t = t.cuda()
        self.dist.all_reduce(t)
        return int(t.item()) == 0

    def average_gradients(self, params: list[torch.nn.Parameter]) -> None:
        """Replace every parameter's gradient by its mean over the ranks (a missing one counts as 0)."""
        if not self.active or not params:
            return
        grads = [p.grad if p.grad is not None else torch.zeros_like(p) for p in params]
        flat = torch.cat([g.reshape(-1) for g in grads])
        self.dist.all_reduce(flat)
        flat /= self.world
        offset = 0
        for p in params:
            n = p.numel()
            p.grad = flat[offset:offset + n].view_as(p).clone()
            offset += n

    def broadcast_module(self, module: torch.nn.Module) -> None:
        """Give every rank rank 0's parameters and buffers."""
        if not self.active:
            return
        with torch.no_grad():
            for t in module.state_dict().values():
                self.dist.broadcast(t, 0)

    def close(self) -> None:
        if self.owned and self.dist.is_initialized():
            self.dist.destroy_process_group()
            self.owned = False
