"""Per-pair evaluation rows gathered from every rank of a distributed run: each pair once, in dataset order.

Lightning gives each rank a DistributedSampler shard (rank r reads items r, r+W, ...), padded by repeating the first
items so that every rank has as many; each row carries its item's ``index`` in the split, so the gathered rows are
de-duplicated and sorted by it. Without a process group the rows are only sorted.
"""

from __future__ import annotations

import torch.distributed as dist

INDEX = "index"


def world_size() -> int:
    return dist.get_world_size() if dist.is_available() and dist.is_initialized() else 1


def gather_rows(rows: list[dict], key: str = INDEX) -> list[dict]:
    """Rows of every rank (each a dict with ``key``): one per distinct ``key``, sorted by it, ``key`` dropped."""
    if world_size() > 1:
        shards: list[list[dict] | None] = [None] * world_size()
        dist.all_gather_object(shards, rows)
        rows = [r for shard in shards for r in shard or []]
    unique: dict[int, dict] = {}
    for r in rows:
        unique.setdefault(int(r[key]), r)  # padding repeats an item: the same pair gives the same values
    return [{k: v for k, v in unique[i].items() if k != key} for i in sorted(unique)]


def gather_sum(value: float) -> float:
    """``value`` summed over the ranks (timings, counts)."""
    if world_size() == 1:
        return value
    out: list[float | None] = [None] * world_size()
    dist.all_gather_object(out, value)
    return float(sum(v or 0.0 for v in out))
