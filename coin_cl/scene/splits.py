"""Which views train and which evaluate, and what each trains on."""

from __future__ import annotations


def split_indices(scene, holdout: int) -> tuple[list[int], list[int]]:
    """(train, eval) view indices: every `holdout`-th training view held out, or the scene's split."""
    if holdout > 0:
        tr = [i for k, i in enumerate(scene.train_idx) if k % holdout != 0]
        te = [i for k, i in enumerate(scene.train_idx) if k % holdout == 0]
        return tr, te
    return list(scene.train_idx), list(scene.test_idx)


def inpainted_targets(scene) -> list:
    """Per-view training targets with the dataset's 2D inpaints where it ships them."""
    rgb = scene.priors.get("rgb", {})
    if not rgb:
        raise ValueError(f"scene {scene.path} has no per-view inpaints (RGB_inpainted/)")
    return [rgb.get(i, img) for i, img in enumerate(scene.images)]
