"""Config -> objects. The DictConfig stops here: everything below takes typed arguments."""

from __future__ import annotations

import torch
from hydra.errors import InstantiationException
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf

from nvs.core import fidelity
from nvs.core.errors import UserError
from nvs.core.protocols import ListsExtras, LossTermLike
from nvs.data.datamodule import NVSDataModule, build_datamodule
from nvs.module.lightning_module import NVSModule


def _instantiate(node, key: str, **kwargs):
    try:
        return instantiate(node, **kwargs)
    except InstantiationException as err:
        # Hydra wraps the real error; name the config key and keep the one-line cause.
        cause = err.__cause__ or err
        raise UserError(f"config '{key}': {cause.__class__.__name__}: {cause}") from None


def build_data(cfg: DictConfig) -> NVSDataModule:
    d = cfg.data
    for key in ("format", "root", "size", "camera", "loader"):
        if key not in d:
            raise UserError(f"config 'data.{key}' is missing")
    if not isinstance(d.size, int) or d.size <= 0:
        raise UserError(f"config 'data.size' must be a positive integer, got {d.size!r}")
    try:
        return build_datamodule(seed=int(cfg.seed), **datamodule_arguments(OmegaConf.to_container(d, resolve=True)))
    except TypeError as err:
        raise UserError(f"config 'data': {err}") from None


def datamodule_arguments(data: dict) -> dict:
    """The data config as ``build_datamodule``'s arguments: what the run reads, and what ``model=mean_depth`` reads
    its training split with."""
    return dict(fmt=data["format"], root=data["root"], size=data["size"], camera=dict(data["camera"]),
                loader=dict(data["loader"]), category=data.get("category"),
                translation_scale=float(data.get("translation_scale", 1.0)),
                max_delta_azimuth=int(data.get("max_delta_azimuth", 40)), train_fraction=data.get("train_fraction", 1.0))


def build_module(cfg: DictConfig, channels_last: bool | None = None) -> NVSModule:
    """The run's module; ``channels_last``: the layout chosen for this run (None: ``cfg.channels_last``, where
    ``auto`` asks nvs.run.precision)."""
    try:
        fidelity.check(OmegaConf.to_container(cfg.fidelity, resolve=True) if cfg.get("fidelity") else None)
    except fidelity.FidelityError as err:
        raise UserError(f"config {err}") from None
    # 'name' labels the model option in tables; everything else is the network's constructor arguments.
    # Component configs interpolate shared nodes (fidelity, data): resolve each against the whole config first.
    model = OmegaConf.to_container(cfg.model, resolve=True)
    net = _instantiate(OmegaConf.create({k: v for k, v in model.items() if k != "name"}), "model", _convert_="all")
    losses = {name: _instantiate(OmegaConf.create(OmegaConf.to_container(node, resolve=True)), f"loss.{name}")
              for name, node in (cfg.get("loss") or {}).items()}
    check_losses(str(cfg.model.get("name", "nvs")), net, losses)
    optimizer = _instantiate(OmegaConf.create(OmegaConf.to_container(cfg.optim, resolve=True)), "optim")
    scheduler = _instantiate(cfg.scheduler, "scheduler") if cfg.get("scheduler") else None
    if channels_last is None:
        channels_last = _layout(cfg)
    module = NVSModule(net, losses, optimizer, nonfinite=cfg.nonfinite, channels_last=channels_last,
                       compile_step=bool(cfg.get("compile", False)),
                       model_name=str(cfg.model.get("name", "nvs")), scheduler=scheduler)
    module.run_config = OmegaConf.to_container(cfg, resolve=True)
    return module


def _layout(cfg: DictConfig) -> bool:
    value = cfg.get("channels_last", "auto")
    return value if isinstance(value, bool) else choose_precision(cfg).channels_last


def choose_precision(cfg: DictConfig):
    """``trainer.precision`` and ``channels_last`` as this run executes them (``auto``: measured, nvs.run.precision)."""
    from nvs.run.precision import choose

    trainer = cfg.get("trainer") or {}
    try:
        return choose(trainer.get("precision", "auto"), cfg.get("channels_last", "auto"),
                      trainer.get("accelerator", "auto"))
    except ValueError as err:
        raise UserError(f"config 'trainer.precision': {err}") from None


def check_losses(model: str, net: torch.nn.Module, losses: dict[str, torch.nn.Module]) -> None:
    """Build time: every enabled loss can be computed on the network's outputs (one clear error otherwise)."""
    check_needs(model, net, losses)
    for name, term in losses.items():
        if isinstance(term, LossTermLike):
            term.check_network(net, f"loss.{name}")


def check_needs(model: str, net: torch.nn.Module, losses: dict[str, torch.nn.Module]) -> None:
    """One clear error when the enabled losses need extras (``term.needs``) that the network does not list in its
    ``provides`` (a network without that list, such as ``NVSNet``, computes every extra)."""
    if not isinstance(net, ListsExtras):
        return
    provides = net.provides
    needs = frozenset().union(*(term.needs for term in losses.values() if isinstance(term, LossTermLike)))
    missing = sorted(needs - frozenset(provides))
    if missing:
        have = ", ".join(sorted(provides)) or "none"
        raise UserError(f"model '{model}' cannot provide {', '.join(repr(m) for m in missing)} that an enabled loss "
                        f"reads; drop that term from loss=[...] (extras this model provides: {have})")


def parameter_count(module: torch.nn.Module) -> int:
    """Trainable parameters of the network (frozen loss networks such as VGG excluded)."""
    return sum(p.numel() for p in module.parameters() if p.requires_grad)
