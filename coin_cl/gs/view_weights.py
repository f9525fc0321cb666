"""Adaptive view weights W_n (CoIn paper 4.2, Ref-GS): lambda_r on the reference view k, a
sigmoid of the change of the view's photometric loss since its previous visit for the others;
`AdaptiveWeightSource` plugs them into the trainer's photometric loss (`coin_cl.gs.terms`)."""

from __future__ import annotations

import math
from typing import Any

from torch import Tensor

from coin_cl.gs.terms import LossContext, ViewWeights


def stable_sigmoid(x: float) -> float:
    """1 / (1 + exp(-x)) without overflow: exp only ever sees a non-positive argument, so huge
    |x| gives exactly 0.0 or 1.0 and never NaN."""
    if x >= 0:
        return 1.0 / (1.0 + math.exp(-x))
    e = math.exp(x)
    return e / (1.0 + e)


class AdaptiveViewWeights:
    """The paper's per-view loss weight W_n (eq. in 4.2).

    W_k = lambda_r for the reference view k; for any other view n
    W_n = 1 / (1 + exp(lambda_r * (L(n, t) - L(n, t-1)))) = sigmoid(-lambda_r * dL), where L(n, t)
    is the view's photometric loss now and L(n, t-1) its loss the previous time it was drawn. A
    view whose loss rose since its last visit (it disagrees with what the other views, led by the
    reference, have built) is down-weighted; one whose loss fell is up-weighted towards 1.

    First visit (no previous loss): `first_visit_weight`, default 0.5 = sigmoid(0), the value the
    formula gives to an unchanged loss, so the first pass neither favours nor punishes a view.
    With `enabled=False` (ablation "w/o adaptive weight") every view, the reference included,
    gets weight 1.0; losses and history are still recorded.

    `weight(view, loss)` must be called once per visit, with the view's unweighted photometric
    loss (a float) before the backward pass; it updates the state. Views are any hashable keys
    (the trainer's view indices).
    """

    def __init__(
        self,
        ref_view: Any,
        lambda_r: float = 50.0,
        first_visit_weight: float = 0.5,
        enabled: bool = True,
    ):
        if not (math.isfinite(lambda_r) and lambda_r > 0):
            raise ValueError(f"lambda_r must be a positive number, got {lambda_r}")
        self.ref_view = ref_view
        self.lambda_r = float(lambda_r)
        self.first_visit_weight = float(first_visit_weight)
        self.enabled = bool(enabled)
        self.prev: dict[Any, float] = {}
        self.history: list[dict[str, Any]] = []

    def formula(self, loss_now: float, loss_prev: float) -> float:
        """sigmoid(-lambda_r * (loss_now - loss_prev)) for a non-reference view."""
        return stable_sigmoid(-self.lambda_r * (loss_now - loss_prev))

    def weight(self, view: Any, loss_now: float | Tensor, step: int | None = None) -> float:
        """The weight of `view` for this visit (and record `loss_now` as its latest loss)."""
        loss = float(loss_now.detach()) if isinstance(loss_now, Tensor) else float(loss_now)
        if not math.isfinite(loss):
            raise ValueError(
                f"view {view!r}: photometric loss is {loss} at step {step}; adaptive weights need a "
                "finite loss (the run has diverged or the target holds NaN/Inf)"
            )
        prev = self.prev.get(view)
        if not self.enabled:
            w = 1.0
        elif view == self.ref_view:
            w = self.lambda_r
        elif prev is None:
            w = self.first_visit_weight
        else:
            w = self.formula(loss, prev)
        self.prev[view] = loss
        self.history.append({"step": step, "view": view, "loss": loss, "prev": prev, "weight": w})
        return w

    def summary(self) -> dict[Any, dict[str, float]]:
        """Per view: visits, mean and last weight (for the JSON log's digest)."""
        out: dict[Any, dict[str, float]] = {}
        for h in self.history:
            s = out.setdefault(h["view"], {"visits": 0, "mean_weight": 0.0, "last_weight": 0.0})
            s["visits"] += 1
            s["mean_weight"] += h["weight"]
            s["last_weight"] = h["weight"]
        for s in out.values():
            s["mean_weight"] /= s["visits"]
        return out

    def state_dict(self) -> dict[str, Any]:
        """Everything needed for a bit-exact resume (plain Python floats: exact in torch.save)."""
        return {
            "ref_view": self.ref_view,
            "lambda_r": self.lambda_r,
            "first_visit_weight": self.first_visit_weight,
            "enabled": self.enabled,
            "prev": dict(self.prev),
            "history": [dict(h) for h in self.history],
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        self.ref_view = sd["ref_view"]
        self.lambda_r = float(sd["lambda_r"])
        self.first_visit_weight = float(sd["first_visit_weight"])
        self.enabled = bool(sd["enabled"])
        self.prev = dict(sd["prev"])
        self.history = [dict(h) for h in sd["history"]]


class AdaptiveWeightSource(ViewWeights):
    """Ref-GS's W_n as a `ViewWeights` source (see `AdaptiveViewWeights`).

    Gets the view's current unweighted photometric loss from `PhotometricLoss`; returns
    W_n x `View.weight` (so a view switched off statically stays off). With
    `weights.enabled=False` (ablation) W_n is 1.0 for every view, the reference included.
    """

    def __init__(self, weights: AdaptiveViewWeights):
        self.weights = weights

    def __call__(self, ctx: LossContext, view_loss: Tensor) -> float:
        return self.weights.weight(ctx.index, view_loss, ctx.step) * float(ctx.view.weight)

    def state_dict(self) -> dict[str, Any]:
        return {"adaptive": self.weights.state_dict()}

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        if "adaptive" in sd:
            self.weights.load_state_dict(sd["adaptive"])
