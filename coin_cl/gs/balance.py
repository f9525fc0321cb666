"""Geometric priors held below the photometric loss in the optimiser's statistics.

A loss term marked `auxiliary` (Ref-GS's reference depth, the background depth) constrains the
geometry where the images cannot (inside the masks). Its gradient can be far larger than the
photometric one, and how much larger follows the prior's units: at the end of an uncapped Ref-GS on
the cup_plain capture, whose depth prior is a GS's depth in scene units, the reference depth term's
gradient norm was 54x the photometric loss's on the reference view and the background depth term's
1.9x (mean over views); on SPIn-NeRF scene 1, whose prior is the dataset's disparity, 1.3x and 0.4x
(`benchmarks/depth_share.py --norms`). Adam divides every parameter's step by the square root of its
second moment, which such a term then fills: on cup_plain the opacity MLP's was 15x a plain
Scaffold-GS's, its photometric steps that much smaller, and the whole view came out blurred (PSNR
outside the masks 27.27 against the plain model's 29.48 at the same 1,375 steps).

`AuxBalance` caps each auxiliary term's share of that moment. Every `every` steps on which a term is
active, the trainer measures the gradient norms (over all trained parameters) of the photometric
part (the sum of the non-auxiliary terms) and of the term, keeps exponential means of their squares
(`EMA` per measurement), and scales the term for the following steps by

    s = min(1, ratio * sqrt(E[|g_main|^2] / (f * E[|g_aux|^2])))

where f is the share of steps the term was active on (the reference depth: one view in N), so that
its contribution to the second moment, f * s^2 * |g_aux|^2, is at most ratio^2 times the
photometric's. s never exceeds 1: a term already below the cap is left alone (SPIn-NeRF's
reference depth). A measurement costs one backward pass per measured term and one for the
photometric part (`torch.autograd.grad`: the parameters' `.grad` stay untouched, and the retained
screen-space gradients the densification reads are put back); the step itself is the usual single
backward of the scaled sum.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import Any

import torch
from torch import Tensor

# The default cap: each auxiliary term holds at most RATIO^2 (1 %) of Adam's second moment, so
# the photometric steps stay within about 1 % of what they would be without the term. Measured on
# cup_plain at a budget-10 run's steps, two seeds (docs/BENCHMARKS.md, "The depth terms' share"):
# against 0.3 (9 %), PSNR more than 20 px from the masks +0.44 / +0.23 dB and in a 20-px ring
# around them +1.28 / +0.33 dB (level with plain Scaffold-GS there), inside the masks m-PSNR
# +0.56 / -0.20 dB, the ghost figure level.
RATIO = 0.1
# Steps between two measurements of one term (each costs one or two backward passes).
EVERY = 25
# Weight of the previous estimate in the exponential means of the squared gradient norms (per
# measurement; at one measurement every 25 steps, a window of about a hundred steps).
EMA = 0.75


def check_ratio(ratio: float) -> float:
    """`ratio` as a float, or a ValueError naming `aux_grad_ratio` (finite, >= 0; 0: no cap)."""
    if not (math.isfinite(ratio) and ratio >= 0):
        raise ValueError(f"aux_grad_ratio must be a finite number >= 0 (0: no cap), got {ratio}")
    return float(ratio)


def grad_norm(value: Tensor, params: Sequence[Tensor]) -> float:
    """The norm of d value / d params over all of `params` (the graph is kept for the step)."""
    grads = torch.autograd.grad(value, list(params), retain_graph=True, allow_unused=True)
    return math.sqrt(sum(float(g.double().pow(2).sum()) for g in grads if g is not None))


class AuxBalance:
    """Scales for the auxiliary loss terms (module doc); state is checkpointed with the trainer.

    Args:
        ratio: the cap on an auxiliary term's root-mean-square gradient relative to the
            photometric part's (0: no cap, every scale 1, nothing measured).
        every: steps between two measurements of one term (it is measured on the first step it is
            active, then on its first active step at least `every` steps after the last).
    """

    def __init__(self, ratio: float = RATIO, every: int = EVERY) -> None:
        if every < 1:
            raise ValueError(f"aux_measure_every must be >= 1, got {every}")
        self.ratio, self.every = check_ratio(ratio), int(every)
        self.scale: dict[str, float] = {}
        self.active: dict[str, int] = {}  # steps the term was active on
        self.measured_at: dict[str, int] = {}
        self.sq_main: dict[str, float] = {}  # EMA of |g_main|^2 at the term's measurements
        self.sq_aux: dict[str, float] = {}  # EMA of |g_term|^2

    def weigh(self, step: int, main: Tensor | None, aux: dict[str, Tensor], params: Sequence[Tensor],
              retained: Sequence[Tensor] = ()) -> dict[str, Tensor]:  # fmt: skip
        """The auxiliary terms' values (name -> weighted scalar) scaled for step `step` (0-based),
        measuring the ones that are due against `main` (the photometric part; None: nothing to
        balance against, scales unchanged). A term counts as active when its value has a graph.
        retained: non-leaf tensors whose `.grad` the step keeps (`retain_grad`: the screen-space
        means the densification reads); `torch.autograd.grad` fills them too, so a measurement
        puts back what they held."""
        if self.ratio == 0 or not aux:
            return aux
        live = {n: v for n, v in aux.items() if v.requires_grad}
        for n in live:
            self.active[n] = self.active.get(n, 0) + 1
        due = [n for n in live if n not in self.measured_at or step - self.measured_at[n] >= self.every]
        if due and main is not None and main.requires_grad:
            held = [t.grad for t in retained]
            gm = grad_norm(main, params) ** 2
            for n in due:
                ga = grad_norm(live[n], params) ** 2
                first = n not in self.measured_at
                self.sq_main[n] = gm if first else EMA * self.sq_main[n] + (1 - EMA) * gm
                self.sq_aux[n] = ga if first else EMA * self.sq_aux[n] + (1 - EMA) * ga
                self.measured_at[n] = step
                f = self.active[n] / (step + 1)
                cap = (
                    self.ratio * math.sqrt(self.sq_main[n] / (f * self.sq_aux[n]))
                    if self.sq_aux[n] > 0
                    else 1.0
                )
                self.scale[n] = min(1.0, cap)
            for t, g in zip(retained, held, strict=True):
                t.grad = g
        return {n: v * self.scale.get(n, 1.0) if n in live else v for n, v in aux.items()}

    def state_dict(self) -> dict[str, Any]:
        return {"scale": dict(self.scale), "active": dict(self.active), "measured_at": dict(self.measured_at),
                "sq_main": dict(self.sq_main), "sq_aux": dict(self.sq_aux)}  # fmt: skip

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.scale = {k: float(v) for k, v in sd.get("scale", {}).items()}
        self.active = {k: int(v) for k, v in sd.get("active", {}).items()}
        self.measured_at = {k: int(v) for k, v in sd.get("measured_at", {}).items()}
        self.sq_main = {k: float(v) for k, v in sd.get("sq_main", {}).items()}
        self.sq_aux = {k: float(v) for k, v in sd.get("sq_aux", {}).items()}
