"""One pass of a network over a loader's pairs that returns per-pair columns (what a rule or a threshold is fitted on),
run by ``trainer.predict`` so that Lightning places the devices and the precision."""

from __future__ import annotations

from collections.abc import Callable

import lightning as L
import torch
import torch.nn as nn

from nvs.core.types import Batch

# columns(net, batch) -> {name: (B,) tensor}
Columns = Callable[[nn.Module, Batch], dict[str, torch.Tensor]]


class PairPass(L.LightningModule):
    """``trainer.predict(PairPass(net, columns), dataloaders=...)`` -> one {name: (B,) float64 CPU tensor} per batch
    (float64: a threshold fitted on these values must compare with the network's own float64 bounds as it did)."""

    def __init__(self, net: nn.Module, columns: Columns):
        super().__init__()
        self.net = net
        self.columns = columns

    def predict_step(self, batch: Batch, batch_idx: int) -> dict[str, torch.Tensor]:
        return {k: v.detach().to("cpu", torch.float64) for k, v in self.columns(self.net, batch).items()}
