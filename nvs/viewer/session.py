"""The viewer's model session: each source image is encoded once; a pose change re-runs only the pose step.

A network with ``encode(src)`` and ``render(encoded, batch)`` (``NVSNet``) is split there; any other network of the
``forward(batch)`` contract (the baselines) runs whole for each view. Execution is the fast mode of training:
channels_last weights and inputs, bf16 autocast on CPU (or float32), under ``inference_mode``.
"""

from __future__ import annotations

import hashlib
import time
from collections import OrderedDict
from dataclasses import dataclass, field

import numpy as np
import torch
import torch.nn as nn

from nvs.core.errors import UserError
from nvs.core.protocols import EncodeOnce
from nvs.core.types import ROUTES
from nvs.viewer.controls import ObjectControls, SceneControls
from nvs.viewer.images import decode_upload, depth_to_uint8, to_uint8



@dataclass
class Source:
    """A source image the page can pick: ``key`` names it in requests, ``meta`` holds its pose (object views)."""

    key: str
    label: str
    image: torch.Tensor  # (3,S,S) uint8
    meta: dict[str, float] = field(default_factory=dict)


@dataclass
class View:
    """One rendered view: images as uint8 arrays, the depth's range, and the model time it took."""

    rgb: np.ndarray  # (S,S,3) uint8
    depth: np.ndarray | None  # (S,S) uint8, near = bright; None for models without depth
    depth_range: tuple[float, float] | None
    model_ms: float  # encoder (when it ran) + pose step + copy to uint8, wall clock
    model_cpu_ms: float  # CPU time of the calling thread for the same work (all of it when torch runs 1 thread)
    encoded: bool  # the encoder ran for this view (a source not seen recently)
    depth_values: np.ndarray | None = None  # (S,S) float32 predicted depth (pose units), for videos and point clouds
    route: str | None = None  # the route a routed view took (copy, warp, full); None: not routed
    route_features: dict[str, float] | None = None  # what the rule read (NaN: not computed for this view)


class ViewSession:
    """The model, its camera and the sources; not thread-safe: the server calls it from one worker thread.

    Args:
        net: a network of the ``forward(batch)`` contract, with ``encode``/``render`` when it can be split.
        K: (3,3) intrinsics at the model's size; pivot: (3,) latent pivot.
        controls: the data format's pose controls.
        gallery: the test-split sources offered on the page.
        autocast: bf16 or None (float32); channels_last: the memory layout (both from nvs.run.precision.choose).
        cache_size: encoded sources (and uploads) kept.
        router: the network behind a fitted route rule (``nvs.models.route.RoutedNet`` of ``net``): ``view(...,
            route=True)`` renders through it, reusing the cached encoding; None: no routing offered.
        compiled: run the pose step (``net.render``) through ``torch.compile`` with inductor's freezing (the weights
            become constants, convolution weights pre-packed); it compiles on the first view. A network that is not
            split, or a compile that fails (one logged line), stays eager. Routed views stay eager.
    """

    def __init__(self, net: nn.Module, image_size: int, K: torch.Tensor, pivot: torch.Tensor,
                 controls: ObjectControls | SceneControls, gallery: list[Source], autocast: torch.dtype | None,
                 cache_size: int = 8, channels_last: bool = True, router: EncodeOnce | None = None,
                 compiled: bool = False):
        if not gallery:
            raise UserError("the dataset's test split has no source images for the gallery")
        self.layout = torch.channels_last if channels_last else torch.contiguous_format
        self.net = net.eval().to(memory_format=self.layout)
        self.image_size = image_size
        self.K, self.pivot = K.float()[None], pivot.float()[None]
        self.controls = controls
        self.gallery = {s.key: s for s in gallery}
        self.autocast = autocast
        self.cache_size = cache_size
        self.uploads: OrderedDict[str, Source] = OrderedDict()
        self._encoded: OrderedDict[str, object] = OrderedDict()
        # Capability, not config: a network that can be split is split.
        self.splits = isinstance(net, EncodeOnce)
        self.encoder_runs = 0
        self.router = router
        self.compiled = bool(compiled and self.splits)
        self._render = torch.compile(self.net.render, dynamic=False) if self.compiled else None

    # -- sources ---------------------------------------------------------------------------------------------------
    def source(self, key: str) -> Source:
        src = self.gallery.get(key) or self.uploads.get(key)
        if src is None:
            raise UserError(f"unknown source '{key}' (uploads are kept for the last {self.cache_size} images)")
        return src

    def add_upload(self, data: bytes, name: str) -> Source:
        """Decode an uploaded file into a source (centre-cropped, resized); the same bytes give the same key."""
        image = decode_upload(data, self.image_size, name)
        key = "upload-" + hashlib.sha1(data).hexdigest()[:12]
        self.uploads[key] = Source(key, name, image, dict(self.controls.upload_meta))
        self.uploads.move_to_end(key)
        while len(self.uploads) > self.cache_size:
            old, _ = self.uploads.popitem(last=False)
            self._encoded.pop(old, None)
        return self.uploads[key]

    # -- rendering -------------------------------------------------------------------------------------------------
    def _context(self):
        return torch.autocast("cpu", dtype=self.autocast or torch.bfloat16, enabled=self.autocast is not None)

    def _src(self, source: Source) -> torch.Tensor:
        return (source.image.float() / 255.0)[None].contiguous(memory_format=self.layout)

    def _encode(self, source: Source) -> tuple[object, bool]:
        """The cached encoding of a source (the source image itself for networks that run whole)."""
        hit = self._encoded.get(source.key)
        if hit is not None:
            self._encoded.move_to_end(source.key)
            return hit, False
        src = self._src(source)
        encoded = self.net.encode(src) if self.splits else src
        self.encoder_runs += self.splits
        self._encoded[source.key] = encoded
        while len(self._encoded) > self.cache_size + len(self.gallery):
            self._encoded.popitem(last=False)
        return encoded, True

    def _eager_step(self, encoded: object, batch: dict) -> dict:
        """The view from a cached encoding: the pose step of a split network, the whole network otherwise."""
        return self.net.render(encoded, batch) if self.splits else self.net({**batch, "src": encoded})

    def _pose_step(self, encoded: object, batch: dict) -> dict:
        if self._render is None:
            return self._eager_step(encoded, batch)
        import torch._inductor.config as inductor

        try:
            with inductor.patch(freezing=True):
                return self._render(encoded, batch)
        except Exception as err:  # noqa: BLE001 - any compiler failure: the eager pose step computes the same view
            print(f"viewer: compile=true: torch.compile failed ({err.__class__.__name__}: {str(err)[:200]}); "
                  "the pose step runs eager", flush=True)
            self._render, self.compiled = None, False
            return self._eager_step(encoded, batch)

    def pose_gflop(self, key: str) -> float:
        """GFLOP (convolutions and matmuls, ``torch.utils.flop_counter``) of one eager pose step of source ``key`` at
        its initial pose: what the encoder-once view costs (the whole network for one that is not split)."""
        from torch.utils.flop_counter import FlopCounterMode

        source = self.source(key)
        batch = self._batch(self.controls.initial(source.meta), source)
        with torch.inference_mode(), self._context():
            encoded, _ = self._encode(source)
            with FlopCounterMode(display=False) as counter:
                self._eager_step(encoded, batch)
        return counter.get_total_flops() / 1e9

    def _batch(self, values: dict[str, float], source: Source) -> dict:
        """The pose part of a batch for the control ``values`` (checked against the trained range)."""
        return {"K": self.K, "T_tgt_src": self.controls.pose(values, source.meta)[None], "pivot": self.pivot}

    def view(self, key: str, values: dict[str, float], route: bool = False) -> View:
        """Render source ``key`` at the pose of the control ``values`` (checked against the trained range); with
        ``route`` through the router (a copied view has no depth: none was predicted)."""
        if route and self.router is None:
            raise UserError("routing is off: start the viewer with route=<a route_rule.json> (nvs.evaluate route=fit)")
        source = self.source(key)
        batch = self._batch(values, source)
        t0, cpu0 = time.perf_counter(), time.thread_time()
        with torch.inference_mode(), self._context():
            encoded, fresh = self._encode(source)
            if route:
                out = self.router.render((self._src(source), encoded), batch)
            else:
                out = self._pose_step(encoded, batch)
            rgb = to_uint8(out["rgb"][0])
            depth = out.get("depth")
            if depth is not None and not bool(torch.isfinite(depth[0]).all()):
                depth = None  # routed to copy: no depth predicted
            grey, span = depth_to_uint8(depth[0]) if depth is not None else (None, None)
            values = depth[0, 0].float().cpu().numpy() if depth is not None else None
            taken = ROUTES[int(out["route"][0])] if "route" in out else None
            features = {k: float(v[0]) for k, v in out["route_features"].items()} if "route" in out else None
        return View(rgb, grey, span, 1000 * (time.perf_counter() - t0), 1000 * (time.thread_time() - cpu0), fresh,
                    values, taken, features)
