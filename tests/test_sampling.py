"""The training order is a function of (seed, epoch, position): a restored loader continues an epoch with exactly the
batches an uninterrupted run trains next, items draw their partner and augmentation from their own seed, and DDP
ranks split one permutation."""

import pytest
import torch

from nvs.data.datamodule import Camera, LoaderSettings, NVSDataModule
from nvs.data.sampling import EpochSampler, ResumableLoader
from nvs.data.shapenet import ObjectsFormat

CAM_OBJ = Camera(fx=480, fy=480, cx=128, cy=128, size=256, pivot=(0.0, 0.0, 2.0))


def _ids(batches):
    return [(tuple(b["id_src"]), tuple(b["id_tgt"])) for b in batches]


def _loader(objects_root, **loader):
    settings = LoaderSettings(batch_size=2, eval_batch_size=2, augment={"mirror": True, "permute_rgb": True}, **loader)
    return NVSDataModule(ObjectsFormat(objects_root, "chair"), CAM_OBJ, 64, settings, seed=3).train_dataloader()


def test_epoch_order_does_not_depend_on_what_ran_before():
    data = list(range(23))
    a, b = EpochSampler(data, seed=5), EpochSampler(data, seed=5)
    for epoch in range(3):
        a.set_epoch(epoch)
        first = list(a)
    b.set_epoch(2)
    assert list(b) == first and list(b) == first  # iterating again gives the same epoch
    assert sorted(i for i, _ in first) == data
    b.set_epoch(1)
    assert list(b) != first
    assert list(EpochSampler(data, seed=6)) != list(EpochSampler(data, seed=5))


def test_ranks_split_one_permutation():
    data = list(range(23))
    shares = [list(EpochSampler(data, seed=1, world=3, rank=r)) for r in range(3)]
    assert all(len(s) == 7 for s in shares)  # 23 // 3: the tail that does not fill every rank is dropped
    flat = [x for s in shares for x in s]
    assert len(set(flat)) == 21 and set(flat) <= set(EpochSampler(data, seed=1))


@pytest.mark.parametrize("num_workers", [0, 1])
def test_a_restored_loader_continues_the_epoch(objects_root, num_workers):
    whole = _loader(objects_root, num_workers=num_workers)
    whole.sampler.set_epoch(1)
    reference = list(whole)
    assert len(reference) == len(whole) >= 4

    torch.manual_seed(123)  # torch's global RNG must not matter
    first = _loader(objects_root, num_workers=num_workers)
    first.sampler.set_epoch(1)
    seen = []
    for batch in first:
        seen.append(batch)
        if len(seen) == 3:
            break
    first.progress = lambda: 3
    state = first.state_dict()
    assert state["epoch"] == 1 and state["batches"] == 3

    torch.manual_seed(7)
    resumed = _loader(objects_root, num_workers=num_workers)
    resumed.load_state_dict(state)
    resumed.sampler.set_epoch(1)  # Lightning's call at the epoch's start keeps the restored position
    rest = list(resumed)
    assert _ids(seen + rest) == _ids(reference)
    for a, b in zip(seen + rest, reference):
        assert torch.equal(a["src"], b["src"]) and torch.equal(a["T_tgt_src"], b["T_tgt_src"])
    assert len(list(resumed)) == len(reference)  # the next pass is a whole epoch again


def test_a_state_saved_at_the_end_of_an_epoch_starts_the_next(objects_root):
    loader = _loader(objects_root)
    loader.progress = lambda: len(loader)
    state = loader.state_dict()
    resumed = _loader(objects_root)
    resumed.load_state_dict(state)
    assert resumed.sampler.epoch == 1 and resumed.sampler.skip == 0
    other = _loader(objects_root)
    other.sampler.set_epoch(1)
    assert list(resumed.sampler) == list(other.sampler)


def test_a_state_of_another_order_is_not_applied(objects_root):
    loader = _loader(objects_root)
    loader.progress = lambda: 2
    state = {**loader.state_dict(), "seed": 99}
    resumed = _loader(objects_root)
    resumed.load_state_dict(state)
    assert resumed.sampler.skip == 0 and resumed.sampler.epoch == 0
    assert ResumableLoader(list(range(4)), batch_size=2).state_dict() == {}


def test_an_item_is_a_function_of_its_seed(objects_root):
    data = _loader(objects_root).dataset
    torch.manual_seed(0)
    a = data[(4, 2**40 + 17)]
    torch.manual_seed(1)
    b = data[(4, 2**40 + 17)]
    assert a["id_tgt"] == b["id_tgt"] and torch.equal(a["src"], b["src"]) and torch.equal(a["K"], b["K"])
    drawn = {data[(4, s)]["id_tgt"] for s in range(40)}
    assert len(drawn) > 1
