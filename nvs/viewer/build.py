"""Config -> the viewer's model session: the checkpoint's network, camera, pose controls and test-split gallery.

Shared by the viewer, ``nvs.render_video`` and ``nvs.export_ply``; the DictConfig stops here.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
from omegaconf import DictConfig

from nvs.core.errors import UserError
from nvs.run.build import build_data
from nvs.run.checkpoints import restore_module, restore_run_config
from nvs.run.precision import choose
from nvs.run.routing import read_rule, routed
from nvs.viewer.controls import build_controls
from nvs.viewer.session import Source, ViewSession


def build_session(cfg: DictConfig, extra_ids: tuple[str, ...] = ()) -> tuple[ViewSession, dict]:
    """The session and what the page shows (model, data, checkpoint, precision).

    The gallery holds ``cfg.gallery`` sources spread over the test split, then ``extra_ids`` (test image ids; one
    that is not in the test split is a UserError).
    """
    if not cfg.ckpt_path:
        raise UserError("give ckpt_path=<a trained checkpoint>, e.g. runs/demo/<time>/checkpoints/last.ckpt")
    try:  # the viewer runs on the CPU: auto is the fastest mode there
        choice = choose(cfg.precision, "auto", accelerator="cpu")
    except ValueError as err:
        raise UserError(f"precision={cfg.precision!r}: {err}") from None
    if choice.precision not in ("32-true", "bf16-mixed"):
        raise UserError(f"precision={cfg.precision!r}: the viewer runs auto, 32-true or bf16-mixed")
    if not isinstance(cfg.gallery, int) or cfg.gallery < 1:
        raise UserError(f"gallery={cfg.gallery!r}: expected a positive number of images")
    run, ckpt = restore_run_config(cfg)
    run.data.loader.with_depth = False  # the viewer shows predicted depth only
    run.loss = {}  # no loss networks (VGG) to build
    datamodule = build_data(run)
    module = restore_module(run, ckpt, channels_last=choice.channels_last)
    test = datamodule.dataset("test")
    controls = build_controls(run.data.format, datamodule)
    ids = list(dict.fromkeys(src for pair in test.pairs for src in pair))
    sources = list(dict.fromkeys(src for src, _ in test.pairs))
    picked = [sources[i] for i in
              sorted(set(np.linspace(0, len(sources) - 1, min(cfg.gallery, len(sources))).round().astype(int)))]
    for fid in extra_ids:
        if fid not in ids:
            raise UserError(f"source={fid!r} is not an image of the test split (e.g. {sources[0]!r})")
        if fid not in picked:
            picked.append(fid)
    gallery = [Source(f"g{i}", fid, test.cache.get(fid)[0], controls.source_meta(fid)) for i, fid in enumerate(picked)]
    router, route = None, None
    if cfg.get("route"):  # a rule fitted by nvs.evaluate route=fit on this checkpoint: the page offers the switch
        rule, payload = read_rule(cfg.route, ckpt)
        router = routed(module, rule)
        route = {"file": str(cfg.route), "rule": payload["rule"], "validation": payload["validation"]}
    session = ViewSession(module.net, int(run.data.size), test.K, test.pivot, controls, gallery,
                          choice.autocast_dtype, channels_last=choice.channels_last, router=router,
                          compiled=bool(cfg.get("compile", False)))
    meta = {"model": module.model_name, "data": run.data.get("name"), "checkpoint": cfg.ckpt_path,
            "precision": choice.precision, "mode": choice.mode, "precision_choice": choice.line(),
            "encoder_once": session.splits, "route": route}
    return session, meta


def source_ids(source: int | str) -> tuple[str, ...]:
    """The test ids ``build_session`` must add to the gallery for ``source`` (a test id that is not a file)."""
    return (str(source),) if isinstance(source, str) and not Path(source).is_file() else ()


def pick_source(session: ViewSession, source: int | str) -> Source:
    """``source`` as the CLIs take it: a gallery index (as on the viewer page; None: the first), an image file
    (treated like an upload: seen from the controls' upload pose), or a test image id (added by ``source_ids``)."""
    if source is None:
        return next(iter(session.gallery.values()))
    if isinstance(source, bool):
        raise UserError(f"source={source!r}: expected a gallery index, a test image id or an image file")
    if isinstance(source, int):
        if not 0 <= source < len(session.gallery):
            n = len(session.gallery)
            raise UserError(f"source={source}: the gallery has {n} images (0..{n - 1})")
        return session.gallery[f"g{source}"]
    path = Path(source)
    if path.is_file():
        return session.add_upload(path.read_bytes(), path.name)
    for s in session.gallery.values():
        if s.label == source:
            return s
    raise UserError(f"source={source!r}: not a gallery index, an image file or a test image id")
