"""Adam with one optimizer per named tensor, per-tensor learning-rate schedules, and row surgery.

Densification adds and removes Gaussians (rows), so every per-Gaussian tensor keeps its own Adam
state that is sliced and padded alongside the parameter (as gsplat does); new rows start with
zero moments so that they are not kicked by their parents' momentum.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import torch
from torch import Tensor, nn

ADAM_EPS = 1e-15  # 3DGS/gsplat: tiny eps so that rarely-seen Gaussians still take full steps


@dataclass(frozen=True)
class ExpSchedule:
    """Log-linear decay from `init` to `final` over `max_steps` (3DGS `get_expon_lr_func`).

    With `delay_steps`, the rate is first multiplied by a cosine ramp from `delay_mult` to 1.
    """

    init: float
    final: float | None = None
    max_steps: int = 30_000
    delay_steps: int = 0
    delay_mult: float = 1.0

    def __call__(self, step: int) -> float:
        final = self.init if self.final is None else self.final
        if self.init == 0.0 and final == 0.0:
            return 0.0
        if self.delay_steps > 0:
            ramp = self.delay_mult + (1 - self.delay_mult) * math.sin(
                0.5 * math.pi * min(max(step / self.delay_steps, 0.0), 1.0)
            )
        else:
            ramp = 1.0
        t = min(max(step / max(self.max_steps, 1), 0.0), 1.0)
        return ramp * math.exp(math.log(self.init) * (1 - t) + math.log(final) * t)

    def scaled(self, factor: float) -> ExpSchedule:
        """The same schedule with both rates multiplied (e.g. by the scene extent)."""
        return ExpSchedule(
            self.init * factor,
            None if self.final is None else self.final * factor,
            self.max_steps,
            self.delay_steps,
            self.delay_mult,
        )


LR = float | ExpSchedule


def continued(lr: LR, done: int, steps: int) -> LR:
    """`lr` for a run that goes on after `done` steps of it: a schedule becomes the decay from its
    rate at `done` to its final rate over the next `steps` steps (once past its end: its final
    rate, held); a constant stays. One stage training a model another left (TE-D after Ref-GS)
    thus continues its decay instead of starting again at the initial rates."""
    if not isinstance(lr, ExpSchedule):
        return lr
    return ExpSchedule(lr(done), lr(lr.max_steps), max(1, steps))


class ParamOptimizer:
    """Named leaf tensors, each with its own Adam and learning-rate schedule.

    Args:
        params: name -> tensor (made an nn.Parameter here if it is not one).
        lrs: name -> constant rate or `ExpSchedule`; a name without an entry is frozen (lr 0).

    `fused` (default True) steps each tensor with torch's fused CPU Adam (one pass over the
    parameter and its moments, 4x faster than the per-op path on 2 cores); the arithmetic is
    Adam's either way and each is deterministic, but the two round differently, so a run resumes
    bit-exactly only on the path it was trained with. False is the earlier per-op path.
    """

    fused: bool = True

    def __init__(self, params: dict[str, Tensor], lrs: dict[str, LR], betas=(0.9, 0.999)):
        self.params: dict[str, nn.Parameter] = {}
        self.optims: dict[str, torch.optim.Adam] = {}
        self.lrs = dict(lrs)
        for name, p in params.items():
            if not isinstance(p, nn.Parameter):
                p = nn.Parameter(p.detach().clone())
            self.params[name] = p
            self.optims[name] = torch.optim.Adam([p], lr=self.lr(name, 0), eps=ADAM_EPS, betas=betas)

    def lr(self, name: str, step: int) -> float:
        v = self.lrs.get(name, 0.0)
        return float(v(step)) if callable(v) else float(v)

    def zero_grad(self) -> None:
        for p in self.params.values():
            p.grad = None

    def step(self, step: int) -> None:
        """Set each tensor's rate for `step`, then take one Adam step on those with gradients."""
        for name, opt in self.optims.items():
            lr = self.lr(name, step)
            p = self.params[name]
            opt.param_groups[0]["lr"] = lr
            # torch 2.13's fused CPU Adam reads a strided gradient as if it were contiguous (silently
            # wrong steps; tests/test_gs_optim.py), so a grad set by hand is made contiguous first.
            fused = self.fused and p.is_contiguous()
            if fused and p.grad is not None and not p.grad.is_contiguous():
                p.grad = p.grad.contiguous()
            opt.param_groups[0]["fused"] = fused
            if lr > 0 and p.grad is not None:
                opt.step()

    # ---- row surgery (per-Gaussian / per-anchor tensors) ----
    def _replace(self, name: str, new: Tensor, state_fn: Callable[[Tensor], Tensor]) -> None:
        old = self.params[name]
        p = nn.Parameter(new.detach().contiguous(), requires_grad=old.requires_grad)
        opt = self.optims[name]
        st = opt.state.pop(old, {})
        for k, v in list(st.items()):
            if k != "step" and isinstance(v, Tensor) and v.shape == old.shape:
                st[k] = state_fn(v)
        opt.param_groups[0]["params"] = [p]
        if st:
            opt.state[p] = st
        self.params[name] = p

    def keep_rows(self, names: list[str], keep: Tensor) -> None:
        """Keep rows where `keep` [N] bool is True, in every named tensor and its Adam moments."""
        for name in names:
            self._replace(name, self.params[name].data[keep], lambda v, k=keep: v[k])

    def append_rows(self, new_rows: dict[str, Tensor]) -> None:
        """Append rows to each named tensor; their Adam moments start at zero."""
        for name, rows in new_rows.items():
            old = self.params[name].data
            self._replace(
                name,
                torch.cat([old, rows.to(old.dtype)], 0),
                lambda v, r=rows: torch.cat([v, v.new_zeros((r.shape[0], *v.shape[1:]))], 0),
            )

    def set_rows(self, name: str, value: Tensor, reset_state: bool = True) -> None:
        """Overwrite a tensor's values (same shape), zeroing its moments (e.g. opacity reset)."""
        self._replace(name, value, (lambda v: torch.zeros_like(v)) if reset_state else (lambda v: v))

    def state_dict(self) -> dict:
        return {
            "params": {k: p.detach().clone() for k, p in self.params.items()},
            "optims": {k: o.state_dict() for k, o in self.optims.items()},
        }

    def load_state_dict(self, sd: dict) -> None:
        """Load values and moments; tensors may have a different row count than now."""
        for name, val in sd["params"].items():
            if name not in self.params:
                raise KeyError(f"checkpoint has parameter {name!r} the model lacks")
            p = self.params[name]
            if p.shape == val.shape:
                with torch.no_grad():
                    p.copy_(val)
            else:
                self._replace(name, val.clone(), lambda v: v)
                p = self.params[name]
            self.optims[name] = torch.optim.Adam([p], lr=self.lr(name, 0), eps=ADAM_EPS)
            self.optims[name].load_state_dict(sd["optims"][name])
