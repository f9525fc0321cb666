"""Gaussian-splatting models and their trainer.

- `GaussianModel` (vanilla 3DGS, gsplat-style densification) and `ScaffoldModel` (Scaffold-GS);
- `photometric_loss` ((1 - 0.2) L1 + 0.2 (1 - SSIM), per-view weights, exclusion masks);
- `ParamOptimizer` / `ExpSchedule` (per-tensor Adam with schedules and row surgery);
- `Trainer`, `TrainConfig`, `make_trainer`, `build_model`, `model_from_state`.
"""

from coin_cl.gs.data import Camera, View, views_from_scene
from coin_cl.gs.gaussians import DensifyConfig, GaussianConfig, GaussianModel
from coin_cl.gs.losses import LossConfig, photometric_loss, ssim_map
from coin_cl.gs.optim import ExpSchedule, ParamOptimizer
from coin_cl.gs.scaffold import ScaffoldConfig, ScaffoldModel
from coin_cl.gs.trainer import (
    TrainConfig,
    Trainer,
    TrainingDivergedError,
    build_model,
    make_trainer,
    model_from_state,
    scaled_model_config,
)

__all__ = [
    "Camera",
    "DensifyConfig",
    "ExpSchedule",
    "GaussianConfig",
    "GaussianModel",
    "LossConfig",
    "ParamOptimizer",
    "ScaffoldConfig",
    "ScaffoldModel",
    "TrainConfig",
    "Trainer",
    "TrainingDivergedError",
    "View",
    "build_model",
    "make_trainer",
    "model_from_state",
    "photometric_loss",
    "scaled_model_config",
    "ssim_map",
    "views_from_scene",
]
