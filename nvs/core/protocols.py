"""What a network and a loss term offer, as ``typing.Protocol``s: the module, the build, the losses, the viewer and the
bench ask these (``isinstance`` on a runtime-checkable protocol) instead of probing attributes by name.

Every network is a :class:`Network`; the others are capabilities a network or a term may add. A new method implements
``Network`` and whichever capabilities it has (docs/extending.md); a type checker checks them structurally.
"""

from __future__ import annotations

from typing import Any, Protocol, runtime_checkable

import torch

from nvs.core.types import Batch, Outputs


@runtime_checkable
class Network(Protocol):
    """``forward(batch, needs) -> outputs``: ``rgb`` (B,3,S,S) in [0,1], ``rgb_scales`` coarse to fine in [-1,1], and
    the extras named in ``needs`` (``nvs.core.types.Extras``) that the enabled losses read."""

    def forward(self, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs: ...


@runtime_checkable
class MultiScale(Protocol):
    """A network that states how many RGB scales it predicts (``len(rgb_scales)``): multi-scale losses check their
    weights against it at build time."""

    n_scales: int


@runtime_checkable
class ListsExtras(Protocol):
    """A network that computes only the extras it lists; a loss needing another one stops the build. A network without
    the list (``NVSNet``) computes every extra."""

    provides: frozenset[str]


@runtime_checkable
class ParamGroups(Protocol):
    """A network that splits its parameters into optimiser groups (a group's ``lr_scale`` multiplies the lr)."""

    def param_groups(self) -> list[dict[str, Any]]: ...


@runtime_checkable
class EncodeOnce(Protocol):
    """A network that encodes a source once and renders any pose from it (the viewer moves the camera this way)."""

    def encode(self, src: torch.Tensor) -> Any: ...

    def render(self, encoded: Any, batch: Batch, needs: frozenset[str] = frozenset()) -> Outputs: ...


@runtime_checkable
class DepthBeforePixels(Protocol):
    """A network that predicts the target depth before, and apart from, its pixel decoder (``NVSNet``): a router
    (``nvs.models.route``) reads the depth and runs ``decode_pixels`` only for the pairs that need it.

    ``predict_depth(encoded, batch) -> (z_t, depth (B,1,S,S))`` and ``decode_pixels(encoded, z_t, depth, batch) ->
    rgb_scales``; both are per sample (any subset of a batch gives that subset's rows)."""

    def encode(self, src: torch.Tensor) -> Any: ...

    def predict_depth(self, encoded: Any, batch: Batch) -> tuple[torch.Tensor, torch.Tensor]: ...

    def decode_pixels(self, encoded: Any, z_t: torch.Tensor, depth: torch.Tensor,
                      batch: Batch) -> list[torch.Tensor]: ...


@runtime_checkable
class DepthRange(Protocol):
    """A depth parameterisation whose every output lies in ``[min_depth, max_depth]`` (the depth heads)."""

    min_depth: float
    max_depth: float


@runtime_checkable
class CountsSkips(Protocol):
    """A component that skips work per sample and counts it: ``skip_fractions`` per level and ``"all"``."""

    def skip_fractions(self) -> dict[str, float]: ...

    def reset_counts(self) -> None: ...


@runtime_checkable
class LossTermLike(Protocol):
    """A loss term: ``term(outputs, batch) -> scalar`` (unweighted), its ``weight`` (the module sums
    ``weight * term``), the extras it reads (``needs``) and its build-time check against the network."""

    weight: float
    needs: frozenset[str]

    def __call__(self, out: Outputs, batch: Batch) -> torch.Tensor: ...

    def check_network(self, net: Any, key: str) -> None: ...


@runtime_checkable
class HasCritic(Protocol):
    """A loss term that trains a critic of its own: stepped on detached predictions before the losses, with its own
    optimiser; returns what it logs."""

    def update_critic(self, out: Outputs, batch: Batch) -> dict[str, torch.Tensor]: ...
