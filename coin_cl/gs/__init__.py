"""Gaussian-splatting models and their trainer.

- `GaussianModel` (vanilla 3DGS) and `ScaffoldModel` (Scaffold-GS): parameters, render, export;
- `DefaultStrategy` / `ScaffoldStrategy` (densification, gsplat's strategy pattern);
- loss terms: `PhotometricLoss` ((1 - 0.2) L1 + 0.2 (1 - SSIM), per-view weights from a
  `ViewWeights` source, exclusion masks), `ScaleVolumeReg`, `NeedleReg`; the protocol in `coin_cl.gs.terms`;
- `ShuffledEpochs` (view sampler);
- `ParamOptimizer` / `ExpSchedule` (per-tensor Adam with schedules and row surgery);
- `build_model`, `scaled_model_config`, `scaled_strategy`, `model_from_state` (the model kinds by name);
- `Trainer`, `TrainConfig`, `make_trainer` (the training loop).
"""

from coin_cl.gs.data import Camera, View, views_from_scene
from coin_cl.gs.gaussians import GaussianConfig, GaussianModel
from coin_cl.gs.losses import LossConfig, photometric_loss, ssim_map
from coin_cl.gs.model_kinds import build_model, model_from_state, scaled_model_config, scaled_strategy
from coin_cl.gs.optim import ExpSchedule, ParamOptimizer
from coin_cl.gs.sampler import ShuffledEpochs, ViewSampler
from coin_cl.gs.scaffold import ScaffoldConfig, ScaffoldModel
from coin_cl.gs.strategy import DefaultStrategy, ScaffoldStrategy, Strategy, default_strategy
from coin_cl.gs.terms import (
    LossContext,
    LossTerm,
    NeedleReg,
    PhotometricLoss,
    ScaleVolumeReg,
    StaticViewWeights,
    ViewWeights,
    default_terms,
)
from coin_cl.gs.trainer import TrainConfig, Trainer, TrainingDivergedError, make_trainer

__all__ = [
    "Camera",
    "DefaultStrategy",
    "ExpSchedule",
    "GaussianConfig",
    "GaussianModel",
    "LossConfig",
    "LossContext",
    "LossTerm",
    "NeedleReg",
    "ParamOptimizer",
    "PhotometricLoss",
    "ScaffoldConfig",
    "ScaffoldModel",
    "ScaffoldStrategy",
    "ScaleVolumeReg",
    "ShuffledEpochs",
    "StaticViewWeights",
    "Strategy",
    "TrainConfig",
    "Trainer",
    "TrainingDivergedError",
    "View",
    "ViewSampler",
    "ViewWeights",
    "build_model",
    "default_strategy",
    "default_terms",
    "make_trainer",
    "model_from_state",
    "photometric_loss",
    "scaled_model_config",
    "scaled_strategy",
    "ssim_map",
    "views_from_scene",
]
