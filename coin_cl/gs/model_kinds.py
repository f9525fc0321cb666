"""The two model kinds by name, '3dgs' (vanilla 3DGS) and 'scaffold' (Scaffold-GS; CoIn paper
section 3, "Preliminary", and docs/DESIGN.md section 6): build a fresh model of a kind, compress its
published schedules (model config and densification, written for 30k steps) to a shorter run as
gsplat's `steps_scaler` does, and rebuild the model a checkpoint holds. A kind's default
densification and loss terms live beside what they choose from (`strategy.default_strategy`,
`terms.default_terms`). The training loop (`coin_cl.gs.trainer.Trainer`) takes a built model and
needs only `model_from_state`, to load a checkpoint.
"""

from __future__ import annotations

from dataclasses import fields, replace
from typing import Any

import numpy as np

from coin_cl.gs.base import Model
from coin_cl.gs.gaussians import GaussianConfig, GaussianModel, gaussian_config_from_dict
from coin_cl.gs.optim import ExpSchedule, continued
from coin_cl.gs.scaffold import ScaffoldConfig, ScaffoldModel, scaffold_config_from_dict
from coin_cl.gs.strategy import DefaultStrategy, ScaffoldStrategy, Strategy

MODELS = ("scaffold", "3dgs")
ModelConfig = GaussianConfig | ScaffoldConfig  # the config of either kind
REFERENCE_ITERS = 30_000  # the step counts the published schedules were written for


def build_model(
    kind: str,
    points: np.ndarray,
    colors: np.ndarray | None,
    extent: float,
    seed: int = 0,
    model_cfg: ModelConfig | None = None,
) -> Model:
    """A fresh 'scaffold' or '3dgs' model from points [N, 3] and optional colours [N, 3]."""
    if kind == "scaffold":
        return ScaffoldModel(points, colors, extent, model_cfg, seed=seed)
    if kind == "3dgs":
        return GaussianModel(points, colors, extent, model_cfg, seed=seed)
    raise ValueError(f"unknown model {kind!r}: use one of {MODELS}")


def scaled_model_config(kind: str, iters: int) -> ModelConfig:
    """Default model config with its schedules compressed to a run of `iters` steps.

    Learning rates decay over exactly `iters`; the SH degree steps shrink by iters / 30k (as
    gsplat's `steps_scaler`), floored at 100. Runs of 30k steps or more get the defaults. The
    densification schedule is scaled by `scaled_strategy`.
    """
    f = min(1.0, iters / REFERENCE_ITERS)
    if kind == "3dgs":
        c = GaussianConfig()
        c.lr_means = replace(c.lr_means, max_steps=iters)
        c.sh_degree_interval = max(100, round(c.sh_degree_interval * f))
        return c
    if kind == "scaffold":
        c2 = ScaffoldConfig()
        return replace(
            c2,
            lr_offsets=replace(c2.lr_offsets, max_steps=iters),
            lr_mlp_opacity=replace(c2.lr_mlp_opacity, max_steps=iters),
            lr_mlp_cov=replace(c2.lr_mlp_cov, max_steps=iters),
            lr_mlp_color=replace(c2.lr_mlp_color, max_steps=iters),
        )
    raise ValueError(f"unknown model {kind!r}: use one of {MODELS}")


def scaled_strategy(kind: str, iters: int) -> Strategy:
    """The default densification of `kind` with its schedule compressed to `iters` steps.

    Start/stop/interval shrink by iters / 30k (gsplat's `steps_scaler`), with floors so that
    statistics still gather over enough views. Runs of 30k steps or more get the defaults.
    """
    f = min(1.0, iters / REFERENCE_ITERS)
    if kind == "3dgs":
        d = DefaultStrategy()
        every = max(20, round(d.refine_every * f))
        return replace(
            d,
            refine_every=every,
            refine_start=max(100, round(d.refine_start * f)),
            refine_stop=max(200, round(d.refine_stop * f)),
            reset_every=max(30 * every, round(d.reset_every * f)),
        )
    if kind == "scaffold":
        c = ScaffoldStrategy()
        every = max(20, round(c.update_interval * f))
        return replace(
            c,
            update_interval=every,
            start_stat=max(50, round(c.start_stat * f)),
            update_from=max(every * 2, round(c.update_from * f)),
            update_until=max(every * 4, round(c.update_until * f)),
        )
    raise ValueError(f"unknown model {kind!r}: use one of {MODELS}")


def continue_rates(model: Model, done: int, steps: int) -> None:
    """Make every learning-rate schedule of `model` go on from step `done` of it to its final rate
    over the next `steps` steps (`optim.continued`), in place; its config too, so that a checkpoint
    written from here on resumes with the same rates. A trainer counts its steps from 0, so without
    this a stage that trains a model further (TE-D after Ref-GS) would start the decay again at the
    initial rates: the offsets' is 100x their final one."""
    model.cfg = replace(model.cfg, **{f.name: continued(getattr(model.cfg, f.name), done, steps)
                                      for f in fields(model.cfg)
                                      if isinstance(getattr(model.cfg, f.name), ExpSchedule)})  # fmt: skip
    # from the config, as a model rebuilt from a checkpoint does: continuing the optimizer's scaled
    # schedules instead rounds differently in the last digit, and a resumed run would drift
    model.optimizer.lrs = model.learning_rates()


def model_from_state(sd: dict[str, Any]) -> Model:
    """Rebuild a model (any size) from its `state_dict`."""
    params = sd["optimizer"]["params"]
    if sd["kind"] == "scaffold":
        cfg = scaffold_config_from_dict(sd["cfg"])
        # the saved anchors are voxelised at their own (resolved) size; the config stays as given
        # (0: automatic), so that a checkpoint written after a resume is the same as without one
        m: Model = ScaffoldModel(params["anchors"].numpy(), None, sd["extent"],
                                 replace(cfg, voxel_size=sd["voxel_size"]))  # fmt: skip
        m.cfg = cfg
    elif sd["kind"] == "3dgs":
        cfg3 = gaussian_config_from_dict(sd["cfg"])
        m = GaussianModel(params["means"].numpy(), None, sd["extent"], cfg3)
    else:
        raise ValueError(f"checkpoint holds an unknown model kind {sd['kind']!r}")
    m.load_state_dict(sd)
    if "carve" in sd:  # the volume a removal keeps empty (`ScaffoldModel.carve`)
        from coin_cl.gs.carve import CarveVolume

        m.carve = CarveVolume.from_state(sd["carve"])
    return m
