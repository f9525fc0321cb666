import pytest
import torch

from coin_cl.gs.sampler import ShuffledEpochs


def test_every_view_once_per_epoch_in_the_previous_order():
    s = ShuffledEpochs(5, seed=1)
    drawn = [s.next() for _ in range(15)]
    for e in range(3):
        assert sorted(drawn[5 * e : 5 * e + 5]) == list(range(5))
    # The order the trainer drew before it had a sampler: permutations popped from the end.
    g = torch.Generator().manual_seed(1)
    old = [i for _ in range(3) for i in reversed(torch.randperm(5, generator=g).tolist())]
    assert drawn == old


def test_state_roundtrip_continues_identically():
    a = ShuffledEpochs(7, seed=3)
    for _ in range(4):  # mid-epoch
        a.next()
    b = ShuffledEpochs(7, seed=99)
    b.load_state_dict(a.state_dict())
    assert [a.next() for _ in range(20)] == [b.next() for _ in range(20)]
    with pytest.raises(ValueError):
        ShuffledEpochs(0)
