"""The one LightningModule: net -> losses -> log; evaluation writes per-image metrics."""

from __future__ import annotations

import math
import time
from collections.abc import Callable

import lightning as L
import torch
import torch.nn as nn
from lightning.pytorch.utilities import rank_zero_warn

from nvs.core.errors import UserError
from nvs.core.protocols import CountsSkips, HasCritic, ParamGroups
from nvs.core.types import Batch
from nvs.core.weights_digest import stamp
from nvs.metrics import per_image as M
from nvs.module.gather import gather_rows, gather_sum
from nvs.module.test_summary import metric_means, route_columns, route_summary


class NonFiniteLossError(UserError, RuntimeError):
    """Raised when the training loss, a gradient or a weight becomes NaN/Inf (and for a loss or a gradient the guard
    is set to stop)."""


def all_finite(tensors: list[torch.Tensor]) -> bool:
    """Every element of every tensor is finite.

    A fused 2-norm per tensor is finite when the tensor is (NaN and inf propagate) and is the fast path (~10 ms for
    the full model's 11.7M weights on 2 CPU threads, where a max-abs takes 140); a norm that overflows on finite
    values over 1e19 is then checked element by element.
    """
    tensors = [t for t in tensors if t.numel()]
    if not tensors:
        return True
    finite = torch.isfinite(torch.stack([n.float() for n in torch._foreach_norm(tensors)]))
    return bool(finite.all()) or all(bool(torch.isfinite(t).all()) for t, ok in zip(tensors, finite.tolist()) if not ok)


class NVSModule(L.LightningModule):
    """Wraps any network with ``forward(batch, needs) -> outputs`` (the paper's model or a baseline).

    Args:
        net: the network.
        losses: name -> loss term (each with ``weight`` and ``needs``).
        optimizer: partial optimizer factory taking the parameters.
        nonfinite: 'stop' raises on a NaN/Inf loss or gradient (the last good checkpoint stays), 'skip' drops that
            step; NaN/Inf weights after a step always stop the run (a diverged run would otherwise score a constant).
        channels_last: run convolutions in channels_last memory format.
        val_metrics: image metrics logged on the validation split (model selection uses ``val/l1``).
        compile_step: ``torch.compile`` the training step's forward and losses together (backward follows the
            compiled graph). A loss list with a critic (adversarial) keeps eager, and a compile that fails falls back
            to eager: each with one logged line.
    """

    def __init__(self, net: nn.Module, losses: dict[str, nn.Module], optimizer: Callable,
                 nonfinite: str = "stop", channels_last: bool = False, val_metrics=("l1", "ssim_paper"),
                 model_name: str = "nvs", scheduler: Callable | None = None, compile_step: bool = False):
        super().__init__()
        if nonfinite not in ("stop", "skip"):
            raise UserError(f"nonfinite={nonfinite!r}: expected 'stop' or 'skip'")
        self.net = net
        self.losses = nn.ModuleDict(losses)
        self.optimizer_factory = optimizer
        self.scheduler_factory = scheduler
        self.nonfinite = nonfinite
        self.channels_last = channels_last
        self.val_metrics = tuple(val_metrics)
        self.model_name = model_name
        # What the enabled losses read, fixed at build time.
        self.train_needs = frozenset().union(*(term.needs for term in losses.values())) if losses else frozenset()
        self.test_rows: list[dict] = []
        self.test_rows_seen: float | None = None  # forwards of all ranks in the last test epoch, padding included
        # the resolved run config, set by the build (nvs.run.build), saved with every checkpoint
        self.run_config: dict | None = None
        self._val_rows: list[dict] = []
        self.test_forward_s = 0.0
        self._constant_terms_warned = False
        self._skipped_grads = False
        if channels_last:
            self.net.to(memory_format=torch.channels_last)
        self._compiled: Callable | None = None
        if compile_step:
            critics = [name for name, term in losses.items() if isinstance(term, HasCritic)]
            if critics:
                rank_zero_warn(f"compile=true: the training step stays eager (loss term(s) {', '.join(critics)} "
                               "step a critic between the forward and the losses)")
            else:
                self._compiled = torch.compile(self._forward_loss)

    def on_fit_start(self) -> None:
        if not self.losses:
            raise UserError("no loss terms enabled: set loss=[...] to at least one of the conf/loss options")
        if not any(p.requires_grad for p in self.net.parameters()):
            raise UserError(f"model '{self.model_name}' has no trainable parameters; evaluate it with nvs.evaluate")

    # -- steps ---------------------------------------------------------------------------------------------------
    def _prepare(self, batch: Batch) -> Batch:
        if self.channels_last:
            for key in ("src", "tgt"):
                batch[key] = batch[key].contiguous(memory_format=torch.channels_last)
        return batch

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()):
        return self.net(self._prepare(batch), needs)

    def _forward_loss(self, batch: Batch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        return self.loss(self(batch, self.train_needs), batch)

    def _compiled_loss(self, batch: Batch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        try:
            return self._compiled(batch)
        except Exception as err:  # noqa: BLE001 - any compiler failure: the eager step computes the same loss
            self._compiled = None
            rank_zero_warn(f"compile=true: torch.compile failed ({err.__class__.__name__}: "
                           f"{str(err).splitlines()[0][:160] if str(err) else ''}); training continues eager")
            return self._forward_loss(batch)

    def training_step(self, batch: Batch, batch_idx: int):
        bs = batch["src"].shape[0]
        if self._compiled is not None:
            total, values = self._compiled_loss(batch)
        else:
            out = self(batch, self.train_needs)
            # Terms that own a critic (adversarial) train it first, on detached predictions, with its own optimiser.
            for name, term in self.losses.items():
                if isinstance(term, HasCritic):
                    for key, value in term.update_critic(out, batch).items():
                        self.log(f"train/{name}/{key}", value, batch_size=bs)
            total, values = self.loss(out, batch)
        for name, value in values.items():
            self.log(f"train/loss/{name}", value.detach(), batch_size=bs)
        if not self._constant_terms_warned:  # checked on the first step only
            self._warn_constant_terms(values)
        self.log("train/loss/total", total.detach(), prog_bar=True, batch_size=bs)
        if not torch.isfinite(total):
            if self.nonfinite == "skip":
                self.log("train/skipped_nonfinite", 1.0, reduce_fx="sum", batch_size=bs)
                return None
            raise NonFiniteLossError(
                f"non-finite training loss at step {self.global_step} "
                f"({', '.join(f'{n}' for n in self.losses)}); the last good checkpoint is kept. "
                "Set nonfinite=skip to drop such steps instead.")
        return total

    def on_before_optimizer_step(self, optimizer) -> None:
        # A non-finite gradient makes the weights non-finite while the loss can still look finite (saturated outputs):
        # caught here like a non-finite loss.
        params = [p for p in self.net.parameters() if p.grad is not None]
        if all_finite([p.grad for p in params]):
            return
        if self.nonfinite == "skip":
            for p in params:  # the optimiser steps no parameter without a gradient
                p.grad = None
            self._skipped_grads = True
            return
        raise NonFiniteLossError(f"non-finite gradient at step {self.global_step}; the last good checkpoint is kept. "
                                 "Lower optim.lr, or set nonfinite=skip to drop such steps.")

    def on_train_batch_end(self, outputs, batch, batch_idx) -> None:
        if self._skipped_grads:
            self._skipped_grads = False
            self.log("train/skipped_nonfinite", 1.0, reduce_fx="sum", batch_size=batch["src"].shape[0])
        # Parameters and floating buffers (normalisation statistics diverge too, from activations out of range).
        state = [t.detach() for t in (*self.net.parameters(), *self.net.buffers()) if t.is_floating_point()]
        if not all_finite(state):
            raise NonFiniteLossError(f"non-finite weights after step {self.global_step} (training diverged); the last "
                                     "good checkpoint is kept. Lower optim.lr.")

    def loss(self, out, batch: Batch) -> tuple[torch.Tensor, dict[str, torch.Tensor]]:
        """The weighted training loss and its raw terms: ``(sum_i w_i * term_i, {name: term_i})``."""
        values = {name: term(out, batch) for name, term in self.losses.items()}
        total = sum(self.losses[name].weight * value for name, value in values.items())
        return total, values

    def _warn_constant_terms(self, values: dict[str, torch.Tensor]) -> None:
        self._constant_terms_warned = True
        constant = [name for name, value in values.items() if torch.is_grad_enabled() and not value.requires_grad]
        if constant:
            rank_zero_warn(f"loss term(s) {', '.join(constant)} depend on no trainable parameter (e.g. "
                           "model/depth=oracle makes the depth terms constants): they are logged but train nothing; "
                           "drop them from loss=[...] to save their compute")

    def validation_step(self, batch: Batch, batch_idx: int):
        out = self(batch)
        values = {name: M.IMAGE_METRICS[name](out["rgb"].float(), batch["tgt"]) for name in self.val_metrics}
        for i, index in enumerate(self._indices(batch, len(self._val_rows))):
            self._val_rows.append({"index": index, **{k: float(v[i]) for k, v in values.items()}})

    def on_validation_epoch_start(self):
        self._val_rows = []

    def on_validation_epoch_end(self):
        # Means over the pairs of every rank, each once (DistributedSampler padding dropped); identical on every
        # rank, and reduced across ranks all the same so that checkpoint selection never sees one shard.
        rows = gather_rows(self._val_rows)
        self._val_rows = []
        for name in self.val_metrics:
            mean = sum(r[name] for r in rows) / len(rows) if rows else float("nan")
            self.log(f"val/{name}", torch.tensor(mean, device=self.device), sync_dist=True)
        # Lightning logs validation a step early (19 for best-20.ckpt): a logged "step" is every logger's x-axis
        self.log("step", float(self.global_step), sync_dist=True)

    @staticmethod
    def _indices(batch: Batch, start: int) -> list[int]:
        """Each item's position in its split (batches built outside the datamodule: in arrival order)."""
        if "index" in batch:
            return [int(i) for i in batch["index"]]
        return list(range(start, start + batch["src"].shape[0]))

    def test_step(self, batch: Batch, batch_idx: int):
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        t0 = time.perf_counter()
        out = self(batch)
        if self.device.type == "cuda":
            torch.cuda.synchronize(self.device)
        self.test_forward_s += time.perf_counter() - t0
        depth_gt = batch.get("depth_tgt")
        depth_pred = out.get("depth") if depth_gt is not None else None
        values = M.compute_all(out["rgb"].float(), batch["tgt"], depth_pred, depth_gt)
        for i, index in enumerate(self._indices(batch, len(self.test_rows))):
            row = {"index": index, "id_src": batch["id_src"][i], "id_tgt": batch["id_tgt"][i]}
            row.update({k: float(v[i]) for k, v in values.items()})
            row.update(route_columns(out, i))
            self.test_rows.append(row)

    def on_test_epoch_end(self):
        # Every rank ends with all the test pairs, once each, in dataset order (nvs.module.gather).
        self.test_rows_seen = gather_sum(float(len(self.test_rows)))
        self.test_forward_s = gather_sum(self.test_forward_s)
        self.test_rows = gather_rows(self.test_rows)
        means = {f"test/{k}": float(v) for k, v in self.test_summary().items()
                 if k != "n_pairs" and v is not None and not math.isnan(v)}
        self.log_dict({**means, "step": float(self.global_step)}, sync_dist=True)  # identical on every rank

    def on_test_epoch_start(self):
        self.test_rows = []
        self.test_forward_s = 0.0
        for counter in self._skip_counters():
            counter.reset_counts()

    def _skip_counters(self) -> list[nn.Module]:
        # Components that skip work per sample (adaptive skips) count what they skipped; see skip_fractions().
        return [m for m in self.net.modules() if isinstance(m, CountsSkips)]

    def test_forward_ms_per_image(self) -> float | None:
        """Forward time alone (no metrics) per test pair of the last test epoch."""
        seen = self.test_rows_seen or len(self.test_rows)  # forwards of all ranks, padding too
        return 1000 * self.test_forward_s / seen if self.test_rows else None

    def test_summary(self) -> dict[str, float]:
        """Mean of every per-image metric over the test pairs (NaN entries, e.g. no valid depth, are ignored), and
        for a model that skips warps the fraction of (sample, level) warps it skipped: ``warp_skipped`` over all
        levels, ``warp_skipped_<level>`` per level; for a routed network the share of pairs of each route,
        ``route_share_<route>``, and its mean L1, ``route_l1_<route>`` (None without pairs)."""
        summary = {**metric_means(self.test_rows), "n_pairs": len(self.test_rows)}
        for counter in self._skip_counters():
            for level, fraction in counter.skip_fractions().items():
                summary["warp_skipped" if level == "all" else f"warp_skipped_{level}"] = fraction
        return {**summary, **route_summary(self.test_rows)}

    def on_save_checkpoint(self, checkpoint: dict) -> None:
        # The resolved run config travels with the weights so that evaluation can rebuild the same network.
        checkpoint["nvs_config"] = self.run_config
        # Frozen loss networks (VGG) are rebuilt from their weight file, not stored 30 MB at a time; terms that train
        # something of their own (an adversarial critic) are kept, so a resumed run continues with them.
        frozen = tuple(f"losses.{name}." for name, term in self.losses.items()
                       if not any(p.requires_grad for p in term.parameters()))
        for key in [k for k in checkpoint["state_dict"] if k.startswith(frozen)]:
            del checkpoint["state_dict"][key]
        weights = [v for v in checkpoint["state_dict"].values() if torch.is_tensor(v) and v.is_floating_point()]
        if not all_finite(weights):  # never a best (or last) checkpoint of a diverged network
            raise NonFiniteLossError(f"non-finite weights at step {self.global_step}: checkpoint not written; the last "
                                     "good checkpoint is kept. Lower optim.lr.")
        stamp(checkpoint)  # the content hash every load checks

    def load_state_dict(self, state_dict, strict: bool = True, assign: bool = False):
        own = {k: v for k, v in super().state_dict().items() if k.startswith("losses.") and k not in state_dict}
        return super().load_state_dict({**state_dict, **own}, strict=strict, assign=assign)

    def configure_optimizers(self):
        # The network's parameters only: a loss term with trainable parts (a critic) steps them with its own optimiser.
        params = [p for p in self.net.parameters() if p.requires_grad]
        # A network may split them into groups with their own settings (Sun et al.: the pixel module at half the lr).
        groups = self.net.param_groups() if isinstance(self.net, ParamGroups) else params
        try:
            optimizer = self.optimizer_factory(groups)
        except ValueError as err:  # torch's own range checks (betas, eps, weight_decay): the user's config
            raise UserError(f"config 'optim': {err}") from None
        for group in optimizer.param_groups:
            group["lr"] *= group.get("lr_scale", 1.0)
        if self.scheduler_factory is None:
            return optimizer
        # Schedules are stepped per optimiser step, so their horizon is trainer.max_steps.
        return {"optimizer": optimizer,
                "lr_scheduler": {"scheduler": self.scheduler_factory(optimizer), "interval": "step"}}
