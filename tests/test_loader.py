"""Loader: shards, per-epoch shuffling, fixed shapes, exact resume, prefetch."""

import numpy as np
import pytest

from irdepth_jax.data.folder import FolderDataset
from irdepth_jax.data.loader import Loader
from irdepth_jax.data.synthetic_dataset import write_synthetic_dataset


class Toy:
    """Dataset of small aligned maps whose values encode the index."""

    def __len__(self):
        return 23

    def __getitem__(self, i):
        seg = (np.arange(30, dtype=np.uint8).reshape(5, 6) + i) % 6
        return dict(ir8=np.full((5, 6), i, np.uint8), seg=seg, depth=seg.astype(np.float32) + 1,
                    valid=seg > 0, id=f"s{i}", labeled=bool(i % 2))


def _run(loader, epochs):
    out = []
    for _ in range(epochs):
        out += [b for b in loader]
    return out


def _eq(a, b):
    assert a.keys() == b.keys()
    for k in a:
        np.testing.assert_array_equal(a[k], b[k])


def test_batches_have_fixed_shapes_and_types():
    b = next(iter(Loader(Toy(), range(23), 4, seed=0, process_index=0, process_count=1)))
    assert b["ir8"].shape == (4, 5, 6) and b["ir8"].dtype == np.uint8
    assert b["valid"].dtype == bool and b["labeled"].shape == (4,)
    assert list(b["id"]) == [f"s{i}" for i in b["index"]]
    np.testing.assert_array_equal(b["ir8"][:, 0, 0], b["index"])
    assert b["mask"].all()


def test_two_process_shards_are_disjoint_and_cover_the_epoch():
    idx = np.arange(3, 23)  # 20 examples
    for drop in (True, False):
        seen = []
        for p in range(2):
            ld = Loader(Toy(), idx, 3, seed=5, drop_remainder=drop, process_index=p,
                        process_count=2)
            batches = list(ld)
            got = np.concatenate([b["index"][b["mask"]] for b in batches])
            assert len(batches) == (3 if drop else 4)
            seen.append(got)
        assert not set(seen[0]) & set(seen[1])
        if drop:  # 10 per process -> 3 full batches each, one example per process dropped
            assert len(seen[0]) == len(seen[1]) == 9
        else:
            assert sorted(np.concatenate(seen)) == list(idx)
    # each global batch of 2 x 3 is the one-process batch of 6: process p holds its p-th block
    a = Loader(Toy(), idx, 3, seed=5, process_index=0, process_count=2)
    b = Loader(Toy(), idx, 3, seed=5, process_index=1, process_count=2)
    one = Loader(Toy(), idx, 6, seed=5, process_index=0, process_count=1)
    for mine, theirs, global_batch in zip(a, b, one):
        np.testing.assert_array_equal(np.r_[mine["index"], theirs["index"]], global_batch["index"])


def test_padding_with_mask_for_evaluation():
    ld = Loader(Toy(), range(7), 3, seed=0, shuffle=False, drop_remainder=False,
                process_index=0, process_count=1)
    batches = list(ld)
    assert [b["ir8"].shape[0] for b in batches] == [3, 3, 3]
    seen = np.concatenate([b["index"][b["mask"]] for b in batches])
    np.testing.assert_array_equal(seen, np.arange(7))
    assert batches[-1]["mask"].tolist() == [True, False, False]


def test_shuffle_per_epoch_and_seed():
    mk = lambda seed: Loader(Toy(), range(23), 5, seed=seed, process_index=0, process_count=1)
    e = [np.concatenate([b["index"] for b in mk(seed)]) for seed in (1, 1, 2)]
    np.testing.assert_array_equal(e[0], e[1])
    assert not np.array_equal(e[0], e[2])
    ld = mk(1)
    first, second = (np.concatenate([b["index"] for b in ld]) for _ in range(2))
    assert not np.array_equal(first, second) and ld.get_state()["epoch"] == 2


@pytest.mark.parametrize("prefetch", [0, 2])
def test_resume_is_exact_with_augmentation(prefetch):
    kw = dict(batch_size=4, seed=3, augment=True, process_index=1, process_count=2,
              prefetch=prefetch)
    full = _run(Loader(Toy(), range(23), **kw), 3)  # 2 batches per epoch, 6 batches
    ld = Loader(Toy(), range(23), **kw)
    head = _run(ld, 1)
    it = iter(ld)
    head.append(next(it))
    state = ld.get_state()
    assert state["epoch"] == 1 and state["index"] == 1
    del it
    resumed = Loader(Toy(), range(23), **kw)
    resumed.set_state(state)
    tail = _run(resumed, 2)
    assert len(head) + len(tail) == len(full)
    for a, b in zip(head + tail, full):
        _eq(a, b)
    # augmentation really happened (some flipped maps) and depends on the epoch
    flipped = [not np.array_equal(b["seg"][0], Toy()[int(b["index"][0])]["seg"]) for b in full]
    assert any(flipped) and not all(flipped)


def test_break_after_last_batch_continues_with_next_epoch():
    ld = Loader(Toy(), range(23), 5, seed=0, process_index=0, process_count=1)
    first = []
    for b in ld:
        first.append(b["index"])
        if len(first) == len(ld):
            break  # the epoch's generator never got to finish
    nxt = next(iter(ld))
    np.testing.assert_array_equal(nxt["index"], ld.epoch_shard(1)[0][:5])
    assert ld.get_state()["epoch"] == 1 and ld.get_state()["index"] == 1


def test_state_validation():
    ld = Loader(Toy(), range(23), 4, seed=0, process_index=0, process_count=1)
    with pytest.raises(ValueError, match="seed"):
        ld.set_state({**ld.get_state(), "seed": 1})
    with pytest.raises(ValueError, match="out of range"):
        ld.set_state({"epoch": 0, "index": 99})
    with pytest.raises(ValueError, match="process_index"):
        Loader(Toy(), range(23), 4, process_index=2, process_count=2)
    with pytest.raises(ValueError, match="no batch"):
        Loader(Toy(), range(3), 4, process_index=0, process_count=1)


def test_defaults_from_jax_and_errors_propagate():
    ld = Loader(Toy(), range(8), 4)  # one process: jax.process_index() 0, process_count() 1
    assert ld.process_index == 0 and ld.process_count == 1

    class Broken(Toy):
        def __getitem__(self, i):
            raise OSError(f"cannot read {i}")

    with pytest.raises(OSError, match="cannot read"):
        list(Loader(Broken(), range(8), 4, process_index=0, process_count=1))


def test_folder_dataset_end_to_end(tmp_path):
    write_synthetic_dataset(tmp_path / "ds", n=8, labeled=0, height=16, width=20, seed=1,
                            progress=False)
    ds = FolderDataset(tmp_path / "ds")
    ld = Loader(ds, ds.indices(split="train"), 2, seed=0, augment=True, process_index=0,
                process_count=1)
    batches = list(ld)
    assert len(batches) == len(ds.indices(split="train")) // 2
    b = batches[0]
    assert b["raw14"].shape == (2, 16, 20) and b["rgb"].shape == (2, 16, 20, 3)
    assert b["condition"].dtype.kind == "U"
