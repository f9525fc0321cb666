"""View samplers: which training view the trainer renders next.

A sampler has `next() -> int` (an index into the trainer's training views) and
`state_dict` / `load_state_dict`, so a resumed run draws the same views as an uninterrupted one.
"""

from __future__ import annotations

from typing import Any

import torch


class ViewSampler:
    """Interface: see `ShuffledEpochs`."""

    def next(self) -> int:
        raise NotImplementedError

    def state_dict(self) -> dict[str, Any]:
        return {}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        pass


class ShuffledEpochs(ViewSampler):
    """Every view once per epoch, in a fresh random order each epoch (3DGS' sampling).

    Args:
        n_views: number of training views.
        seed: seeds the permutations (the trainer passes its seed + 1).
    """

    def __init__(self, n_views: int, seed: int = 0):
        if n_views <= 0:
            raise ValueError("no training views")
        self.n_views = n_views
        self.gen = torch.Generator().manual_seed(seed)
        self.perm: list[int] = []

    def next(self) -> int:
        if not self.perm:
            self.perm = torch.randperm(self.n_views, generator=self.gen).tolist()
        return self.perm.pop()

    def state_dict(self) -> dict[str, Any]:
        return {"gen": self.gen.get_state(), "perm": list(self.perm)}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.gen.set_state(sd["gen"])
        self.perm = list(sd["perm"])
