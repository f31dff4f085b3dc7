"""Training order that a killed run resumes exactly: every epoch's order and every item's random draws are functions of
(seed, epoch, position), and the loader's state in a checkpoint is where in the epoch training stood.

``EpochSampler`` yields ``(index, item_seed)``: the permutation of epoch ``e`` and the items' seeds come from one
generator seeded by (seed, e), so they do not depend on how many epochs ran in this process, on the number of loader
workers, or on torch's global RNG. ``PairDataset`` draws a training item's partner view and augmentation from its
``item_seed``. ``ResumableLoader`` is a DataLoader with Lightning's ``state_dict``/``load_state_dict`` interface: the
state is the epoch and the batches already trained in it (Lightning's own progress counter), and a restored loader
skips those batches, so the resumed run sees the same batches as an uninterrupted one.

The sampler is a ``DistributedSampler``: under DDP each rank takes every ``world``-th item of the same permutation
(Lightning keeps a sampler of that type instead of wrapping it), and a single process is ``world = 1``.
"""

from __future__ import annotations

from typing import Callable, Iterator

import torch
from torch.utils.data import DataLoader, Dataset, DistributedSampler


class EpochSampler(DistributedSampler):
    """A seeded shuffle per epoch, sharded over ``world`` ranks, dropping the tail that does not fill every rank."""

    def __init__(self, dataset: Dataset, seed: int, world: int = 1, rank: int = 0):
        super().__init__(dataset, num_replicas=world, rank=rank, shuffle=True, seed=seed, drop_last=True)
        self.skip = 0  # items of this rank's share of the current epoch already trained (a restored state)

    def set_epoch(self, epoch: int) -> None:
        if epoch != self.epoch:
            self.skip = 0
        super().set_epoch(epoch)

    def epoch_draws(self, epoch: int) -> tuple[torch.Tensor, torch.Tensor]:
        """(order, item seeds) of ``epoch`` over the whole dataset, before sharding."""
        g = torch.Generator().manual_seed(self.seed * 1_000_003 + epoch)
        n = len(self.dataset)
        return torch.randperm(n, generator=g), torch.randint(0, 2**62, (n,), generator=g)

    def __iter__(self) -> Iterator[tuple[int, int]]:
        order, seeds = self.epoch_draws(self.epoch)
        picked = torch.arange(self.rank, self.total_size, self.num_replicas)
        skip, self.skip = self.skip, 0
        for position in picked[skip:].tolist():
            yield int(order[position]), int(seeds[position])


class ResumableLoader(DataLoader):
    """A DataLoader over an :class:`EpochSampler` whose checkpointed state resumes the epoch where it stood.

    ``progress`` returns the batches trained so far in the current epoch (set by the data module from the trainer's
    loop); without it the state is empty and a restored run starts its epoch over.
    """

    progress: Callable[[], int] | None = None

    def state_dict(self) -> dict:
        if self.progress is None or not isinstance(self.sampler, EpochSampler):
            return {}
        return {"epoch": int(self.sampler.epoch), "batches": int(self.progress()), "batch_size": self.batch_size,
                "seed": int(self.sampler.seed)}

    def load_state_dict(self, state: dict) -> None:
        sampler = self.sampler
        if not state or not isinstance(sampler, EpochSampler):
            return
        if state.get("seed") != sampler.seed or state.get("batch_size") != self.batch_size:
            return  # another order than the checkpoint's: there is no position in it to resume
        epoch, batches = int(state["epoch"]), int(state["batches"])
        if batches >= len(self):  # saved after the epoch's last batch: the next epoch starts from its beginning
            epoch, batches = epoch + 1, 0
        sampler.set_epoch(epoch)
        sampler.skip = batches * int(self.batch_size)
