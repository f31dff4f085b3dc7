"""One LightningDataModule for both formats: builds (src, tgt) pair datasets that yield the batch contract."""

from __future__ import annotations

import random
from dataclasses import dataclass
from typing import Protocol

import lightning as L
import torch
from torch.utils.data import DataLoader, Dataset

from nvs.core.errors import DataError, UserError
from nvs.core.geometry import scale_intrinsics
from nvs.data.files import depth_problem, image_problem
from nvs.data.kitti import ScenesFormat
from nvs.data.sampling import EpochSampler, ResumableLoader
from nvs.data.shapenet import ObjectsFormat, object_pairs, random_partner


class Format(Protocol):
    has_depth: bool

    def references(self, split: str, val_fraction: float, seed: int) -> list[tuple]: ...

    def image_path(self, fid: str): ...

    def depth_path(self, fid: str): ...

    def read(self, fid: str, size: int, with_depth: bool) -> tuple[torch.Tensor, torch.Tensor | None]: ...

    def pose(self, tgt: str, src: str) -> torch.Tensor: ...


@dataclass
class Camera:
    """Camera facts of a dataset (from the data config): intrinsics at a reference size and the latent pivot."""

    fx: float
    fy: float
    cx: float
    cy: float
    size: int  # resolution the intrinsics are given at
    pivot: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def K(self, size: int) -> torch.Tensor:
        K = torch.tensor([[self.fx, 0.0, self.cx], [0.0, self.fy, self.cy], [0.0, 0.0, 1.0]])
        return scale_intrinsics(K, size / self.size)


class ViewCache:
    """Decoded views kept in memory as uint8 (images) so that every view is decoded once per process."""

    def __init__(self, fmt: Format, size: int, with_depth: bool, enabled: bool):
        self.fmt, self.size, self.with_depth, self.enabled = fmt, size, with_depth, enabled
        self._store: dict[str, tuple[torch.Tensor, torch.Tensor | None]] = {}

    def get(self, fid: str) -> tuple[torch.Tensor, torch.Tensor | None]:
        hit = self._store.get(fid)
        if hit is None:
            hit = self.fmt.read(fid, self.size, self.with_depth)
            if self.enabled:
                self._store[fid] = hit
        return hit


_MIRROR = torch.diag(torch.tensor([-1.0, 1.0, 1.0, 1.0]))


def mirror_pair(item: dict) -> dict:
    """The same pair seen in a mirror (x -> -x): images and depths flipped left-right, K, pose and pivot to match.

    With M = diag(-1,1,1) the mirrored cameras see M·X, so T' = M T M, pivot' = M pivot and cx' = W-1-cx (pixel
    centres at integer coordinates): inverse-warping the mirrored pair equals mirroring the warped pair.
    """
    out = dict(item)
    for key in ("src", "tgt", "depth_src", "depth_tgt"):
        if key in item:
            out[key] = item[key].flip(-1)
    K = item["K"].clone()
    K[0, 2] = item["src"].shape[-1] - 1 - K[0, 2]
    out["K"] = K
    out["T_tgt_src"] = _MIRROR @ item["T_tgt_src"] @ _MIRROR
    out["pivot"] = item["pivot"] * _MIRROR[:3, :3].diagonal()
    return out


class PairDataset(Dataset):
    """(src, tgt) pairs -> batch items. ``pairs`` is a fixed list, or ``sources`` + ``partner`` draw a target per item.

    ``augment`` (training only): ``mirror`` flips half the pairs left-right with the geometry to match
    (:func:`mirror_pair`); ``permute_rgb`` applies one random permutation of the colour channels to both views.
    """

    def __init__(self, cache: ViewCache, camera: Camera, pairs=None, sources=None, partner=None,
                 augment: dict | None = None):
        self.cache, self.camera = cache, camera
        self.pairs, self.sources, self.partner = pairs, sources, partner
        self.augment = augment or {}
        self.K = camera.K(cache.size)
        self.pivot = torch.tensor(camera.pivot, dtype=torch.float32)

    def __len__(self) -> int:
        return len(self.pairs) if self.pairs is not None else len(self.sources)

    def __getitem__(self, key: int | tuple[int, int]) -> dict:
        """``key``: an index, or (index, item seed) from :class:`~nvs.data.sampling.EpochSampler`, whose seed decides
        the item's partner and augmentation (otherwise torch's RNG, seeded per worker by Lightning, does)."""
        i, item_seed = key if isinstance(key, tuple) else (key, None)
        g = None if item_seed is None else torch.Generator().manual_seed(item_seed)
        if self.pairs is not None:
            src_id, tgt_id = self.pairs[i]
        else:
            src_id = self.sources[i]
            draw = item_seed if item_seed is not None else int(torch.randint(0, 2**31 - 1, ()))
            tgt_id = self.partner(src_id, random.Random(draw))
        src, d_src = self.cache.get(src_id)
        tgt, d_tgt = self.cache.get(tgt_id)
        item = {
            "src": src.float() / 255.0,
            "tgt": tgt.float() / 255.0,
            "K": self.K.clone(),
            "T_tgt_src": self.cache.fmt.pose(tgt_id, src_id),
            "pivot": self.pivot.clone(),
            "id_src": src_id,
            "id_tgt": tgt_id,
            # position in the split: evaluation under DDP gathers rows by it (sampler padding repeats indices)
            "index": i,
        }
        if d_src is not None:
            item["depth_src"], item["depth_tgt"] = d_src, d_tgt
        if self.augment.get("mirror") and bool(torch.randint(0, 2, (), generator=g)):
            item = mirror_pair(item)
        if self.augment.get("permute_rgb"):
            order = torch.randperm(3, generator=g)
            item["src"], item["tgt"] = item["src"][order], item["tgt"][order]
        return item


@dataclass
class LoaderSettings:
    batch_size: int = 8
    eval_batch_size: int = 16
    num_workers: int = 0
    val_fraction: float = 0.1
    val_pairs_per_model: int = 4
    cache: bool = True
    with_depth: bool = True  # load ground-truth depth when the dataset has it
    limit_test_pairs: int | None = None
    # training-pair augmentation: {mirror: bool, permute_rgb: bool} (see PairDataset)
    augment: dict | None = None

    def __post_init__(self):
        for key in ("batch_size", "eval_batch_size", "val_pairs_per_model"):
            value = getattr(self, key)
            if isinstance(value, bool) or not isinstance(value, int) or value < 1:
                raise UserError(f"data.loader.{key}={value!r}: expected a positive integer")
        if isinstance(self.num_workers, bool) or not isinstance(self.num_workers, int) or self.num_workers < 0:
            raise UserError(f"data.loader.num_workers={self.num_workers!r}: expected an integer >= 0")
        if not 0 <= self.val_fraction < 1:
            raise UserError(f"data.loader.val_fraction={self.val_fraction!r}: expected a fraction in [0, 1)")
        if self.limit_test_pairs is not None and self.limit_test_pairs < 1:
            raise UserError(f"data.loader.limit_test_pairs={self.limit_test_pairs!r}: expected null or >= 1")
        unknown = set(self.augment or {}) - {"mirror", "permute_rgb"}
        if unknown:
            raise UserError(f"data.loader.augment: unknown key(s) {sorted(unknown)}; expected mirror, permute_rgb")


FULL_CHECK_IMAGES = 50_000


class NVSDataModule(L.LightningDataModule):
    """Train / val / test pair datasets for one dataset root in either format."""

    def __init__(self, fmt: Format, camera: Camera, size: int, loader: LoaderSettings, seed: int = 0,
                 max_delta_azimuth: int = 40, train_fraction: float = 1.0):
        super().__init__()
        if size % 16:
            raise UserError(f"data.size={size} must be divisible by 16")
        if (isinstance(train_fraction, bool) or not isinstance(train_fraction, (int, float))
                or not 0 < train_fraction <= 1):
            raise UserError(f"data.train_fraction={train_fraction!r}: expected a fraction in (0, 1]")
        if train_fraction < 1 and not isinstance(fmt, ObjectsFormat):
            raise UserError("data.train_fraction < 1 is for the objects format (a subset of training models)")
        self.train_fraction = train_fraction
        self.fmt, self.camera, self.size, self.loader = fmt, camera, size, loader
        self.seed, self.max_delta_azimuth = seed, max_delta_azimuth
        self._sets: dict[str, PairDataset] = {}

    def dataset(self, split: str) -> PairDataset:
        if split not in self._sets:
            with_depth = self.loader.with_depth and self.fmt.has_depth
            cache = ViewCache(self.fmt, self.size, with_depth, self.loader.cache)
            # One cache shared across splits: views are decoded once.
            if self._sets:
                cache = next(iter(self._sets.values())).cache
            self._sets[split] = self._build(split, cache)
        return self._sets[split]

    def validate(self, splits=("train", "val", "test")) -> None:
        """Check every list of ``splits`` and every file it references (images; depths when loaded) before any
        step: raises DataError naming the list file and the line of the bad entry. Reads headers, not pixels."""
        with_depth = self.loader.with_depth and self.fmt.has_depth
        refs = {split: self.fmt.references(split, self.loader.val_fraction, self.seed) for split in splits}
        # Every image is opened and checksummed up to FULL_CHECK_IMAGES; beyond, training views are only stat()ed
        # (the test views and each entry's first view still are), so that a full-size ShapeNet checks in seconds.
        full = sum(len(ids) for entries in refs.values() for *_, ids in entries) <= FULL_CHECK_IMAGES
        for split, entries in refs.items():
            for list_path, line, what, ids in entries:
                for fid in ids:
                    image = self.fmt.image_path(fid)
                    problem = image_problem(image, header=full or split == "test" or fid == ids[0])
                    if problem is None and with_depth:
                        image = self.fmt.depth_path(fid)
                        problem = depth_problem(image, self.size)
                    if problem:
                        raise DataError(list_path, f"{what}: {problem}: {image}", line)

    def test_pairs(self) -> list[tuple[str, str]]:
        """The (source, target) view ids the test split evaluates, in order: the ids test_per_image.csv lists.
        Reads the list files only (no image)."""
        if isinstance(self.fmt, ObjectsFormat):
            pairs = self.fmt.test_pairs()
        else:
            pairs = self.fmt.pairs("test", self.loader.val_fraction, self.seed)
        if self.loader.limit_test_pairs:
            pairs = pairs[: self.loader.limit_test_pairs]
        return [(str(a), str(b)) for a, b in pairs]

    def _build(self, split: str, cache: ViewCache) -> PairDataset:
        lo = self.loader
        if split == "test":
            return PairDataset(cache, self.camera, pairs=self.test_pairs(), augment=None)
        if not isinstance(self.fmt, ObjectsFormat):
            pairs = self.fmt.pairs(split, lo.val_fraction, self.seed)
            return PairDataset(cache, self.camera, pairs=pairs, augment=lo.augment if split == "train" else None)
        models = self.fmt.split_models(split, lo.val_fraction, self.seed)
        if split == "val":
            pairs = object_pairs(models, self.fmt, lo.val_pairs_per_model, self.max_delta_azimuth, self.seed)
            return PairDataset(cache, self.camera, pairs=pairs, augment=None)
        models = train_subset(models, self.train_fraction, self.seed)
        sources = [v for m in models for v in self.fmt.views(m)]
        d = self.max_delta_azimuth
        return PairDataset(cache, self.camera, sources=sources, partner=lambda s, rng: random_partner(s, d, rng),
                           augment=lo.augment)

    def _loader(self, split: str, batch_size: int) -> DataLoader:
        return DataLoader(self.dataset(split), batch_size=batch_size, shuffle=False,
                          num_workers=self.loader.num_workers, persistent_workers=self.loader.num_workers > 0)

    def train_dataloader(self) -> ResumableLoader:
        """Shuffled by (seed, epoch), sharded over the trainer's ranks, resumed mid-epoch (nvs.data.sampling)."""
        trainer = self.trainer
        world, rank = (trainer.world_size, trainer.global_rank) if trainer is not None else (1, 0)
        data = self.dataset("train")
        sampler = EpochSampler(data, self.seed, world, rank)
        loader = ResumableLoader(data, batch_size=self.loader.batch_size, sampler=sampler,
                                 num_workers=self.loader.num_workers, drop_last=True,
                                 persistent_workers=self.loader.num_workers > 0)
        if trainer is not None:
            loader.progress = lambda: trainer.fit_loop.epoch_loop.batch_progress.current.processed
        return loader

    def val_dataloader(self):
        return self._loader("val", self.loader.eval_batch_size)

    def test_dataloader(self):
        return self._loader("test", self.loader.eval_batch_size)


def train_subset(models: list[str], fraction: float, seed: int) -> list[str]:
    """A seeded subset of round(fraction * n) >= 1 training models (sorted); smaller fractions are nested in larger
    ones under one seed (a prefix of one seeded order), so a data-scale study adds models as the fraction grows."""
    if fraction >= 1:
        return list(models)
    order = sorted(models)
    random.Random(f"train_fraction/{seed}").shuffle(order)
    return sorted(order[: max(1, round(fraction * len(order)))])


def build_datamodule(fmt: str, root: str, size: int, camera: dict, loader: dict, seed: int = 0,
                     category: str | None = None, translation_scale: float = 1.0,
                     max_delta_azimuth: int = 40, train_fraction: float = 1.0) -> NVSDataModule:
    """Typed construction from the data config (``fmt`` is 'objects' or 'scenes')."""
    cam = Camera(**camera)
    settings = LoaderSettings(**loader)
    if fmt == "objects":
        if not category:
            raise UserError("data.category is required for the objects format")
        f: Format = ObjectsFormat(root, category, centre=tuple(cam.pivot))
    elif fmt == "scenes":
        f = ScenesFormat(root, translation_scale)
    else:
        raise UserError(f"data.format={fmt!r}: expected 'objects' or 'scenes'")
    return NVSDataModule(f, cam, size, settings, seed=seed, max_delta_azimuth=max_delta_azimuth,
                         train_fraction=train_fraction)


__all__ = ["Camera", "LoaderSettings", "NVSDataModule", "PairDataset", "build_datamodule", "train_subset"]
