"""Scenes: cameras, images, masks and sparse points from COLMAP / SPIn-NeRF folders, plus an
embedded synthetic scene with ground truth. Conventions live in `coin_cl.scene.conventions`."""

from .loader import image_sizes, load_scene, save_scene
from .masks import bbox_mask, check_mask, derive_mask, dilate_mask, read_mask, scribble_mask
from .ply import read_points_ply, write_points_ply
from .synthetic import make_synthetic, write_synthetic
from .types import Camera, Scene

__all__ = [
    "Camera",
    "Scene",
    "bbox_mask",
    "check_mask",
    "derive_mask",
    "dilate_mask",
    "image_sizes",
    "load_scene",
    "make_synthetic",
    "read_mask",
    "read_points_ply",
    "save_scene",
    "scribble_mask",
    "write_points_ply",
    "write_synthetic",
]
