"""One process, or one rank of ``torchrun``: chosen by the environment (``RANK`` set or not).

    python -m training.train --out runs/mine                        # one process
    torchrun --standalone --nproc_per_node 2 -m training.train --out runs/mine   # two ranks

Under ``torchrun`` each rank joins the process group (NCCL on GPUs, one per local rank; gloo on
the CPU), trains a ``DistributedDataParallel`` copy of the model on its share of every batch,
and the gradients are averaged across ranks. Each share's loss is weighted by its size, so a
step is the step one process takes on the whole batch, whatever the number of ranks.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import numpy as np
import torch
import torch.distributed as dist
from torch.nn.parallel import DistributedDataParallel


@dataclass(frozen=True)
class Ranks:
    rank: int = 0
    world: int = 1
    device: torch.device = torch.device("cpu")

    @classmethod
    def from_environment(cls) -> Ranks:
        """This process's rank, joined to the group when ``torchrun`` started it."""
        cuda = torch.cuda.is_available()
        if "RANK" not in os.environ:
            return cls(device=torch.device("cuda" if cuda else "cpu"))
        local = int(os.environ.get("LOCAL_RANK", "0"))
        if cuda:
            torch.cuda.set_device(local)
        dist.init_process_group("nccl" if cuda else "gloo")
        device = torch.device(f"cuda:{local}" if cuda else "cpu")
        return cls(dist.get_rank(), dist.get_world_size(), device)

    @property
    def main(self) -> bool:
        """The rank that writes the log, the config and the checkpoints."""
        return self.rank == 0

    def wrap(self, model: torch.nn.Module) -> torch.nn.Module:
        """The model that trains: ``DistributedDataParallel`` across ranks, else itself."""
        if self.world == 1:
            return model
        device_ids = [self.device.index] if self.device.type == "cuda" else None
        return DistributedDataParallel(model, device_ids=device_ids)

    def batches(self, order: np.ndarray, size: int) -> list[np.ndarray]:
        """The epoch's batches, each with at least one item per rank (a shorter last batch is
        dropped under ``torchrun``: a rank without data cannot take part in the step)."""
        batches = [order[i : i + size] for i in range(0, len(order), size)]
        return [batch for batch in batches if len(batch) >= self.world]

    def share(self, count: int) -> slice:
        """This rank's positions in a batch of ``count``: contiguous, sizes within one."""
        edges = np.linspace(0, count, self.world + 1).round().astype(int)
        return slice(edges[self.rank], edges[self.rank + 1])

    def weight(self, count: int) -> float:
        """What this rank's mean loss is multiplied by, so that the gradients averaged across
        ranks are the gradient of the whole batch's mean: its share of the batch, times the
        number of ranks."""
        share = self.share(count)
        return (share.stop - share.start) * self.world / count

    def total(self, values: np.ndarray) -> np.ndarray:
        """The sum of ``values`` over the ranks."""
        if self.world == 1:
            return values
        tensor = torch.tensor(values, dtype=torch.float64, device=self.device)
        dist.all_reduce(tensor)
        return tensor.cpu().numpy()

    def close(self) -> None:
        """Leave the group together: a rank that tore its group down while another was still
        writing its checkpoint was once aborted by gloo ("terminate called without an active
        exception", tests/training/test_training.py on a busy machine)."""
        if self.world > 1 or dist.is_initialized():
            dist.barrier()
            dist.destroy_process_group()
