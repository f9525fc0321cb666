"""360-USID folders (AuraFusion360's 360-degree removal benchmark) -> `Scene`.

The layout, as the public loaders read it (FreeInpaint's `datasets/USID_loader.py`; AuraFusion360's
`scripts/aura_eval.py` for test_images/):

    scene/
      images/<name>             training views, WITH the object
      object_masks/<name>       their object masks (same file name; non-zero / >= half range = object)
      test_images/<name>        object-ABSENT test views (ground truth), posed in the same model
      <scene>_masks/<k:05d>.png optional test masks: k = the test image's rank by name, from 0
      reference/<name>          optional: the reference view (the first by name), a training view
      sparse/0/                 COLMAP model holding every training and test image

Poses and the rest are the COLMAP folder's (`folder.py`); only the file lists, the split and the
mask lookup differ.
"""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np

from .folder import ImageFolder, _load_image_folder, find_file, open_folder
from .io import list_images
from .masks import read_mask
from .types import Scene

log = logging.getLogger(__name__)

TEST_IMAGES = "test_images"
OBJECT_MASKS = "object_masks"
REFERENCE = "reference"
TEST_MASKS_SUFFIX = "_masks"


def is_usid(root: Path) -> bool:
    """A 360-USID folder: test_images/ and object_masks/ beside images/."""
    return (root / TEST_IMAGES).is_dir() and (root / OBJECT_MASKS).is_dir()


def _test_mask_dir(root: Path) -> Path | None:
    dirs = sorted(d for d in root.glob(f"*{TEST_MASKS_SUFFIX}") if d.is_dir() and d.name != OBJECT_MASKS)
    if len(dirs) > 1:
        raise ValueError(
            f"{root}: several test-mask folders ({', '.join(d.name for d in dirs)}); keep the one named "
            f"<scene>{TEST_MASKS_SUFFIX}"
        )
    return dirs[0] if dirs else None


def load_usid_folder(folder: ImageFolder, **opts) -> Scene:
    """360-USID (module doc): training views from images/ with object_masks/, test views from
    test_images/ with `<scene>_masks/<k:05d>.png` when present; `opts`: load_scene's undistort,
    n_test (ignored: the split is the folders'), mask_dilate, priors."""
    root = folder.root
    test_files = list_images(root / TEST_IMAGES)
    if not test_files:
        raise FileNotFoundError(f"{root / TEST_IMAGES} holds no .png/.jpg images (360-USID test views)")
    train_stems = {f.stem for f in folder.files}
    clash = [f.name for f in test_files if f.stem in train_stems]
    if clash:
        raise ValueError(
            f"{root}: {clash[0]} is both a training image and a test image; outputs are named by the stem"
        )
    full = open_folder(root, folder.imgdir, folder.files + test_files)
    is_test_file = [f.parent.name == TEST_IMAGES for f in full.files]
    test_rank = {f.name: k for k, f in enumerate(sorted(test_files, key=lambda p: p.name))}
    tmask_dir = _test_mask_dir(root)
    obj_dir = root / OBJECT_MASKS

    def mask_fn(
        fo: ImageFolder, i: int, f: Path, is_test: bool, shape
    ) -> tuple[np.ndarray | None, Path | None]:
        if is_test_file[i]:
            if tmask_dir is None:
                return None, None
            mp = tmask_dir / f"{test_rank[f.name]:05d}.png"
            if not mp.is_file():
                raise FileNotFoundError(
                    f"test mask {mp} for {f} not found (k = rank of the test image by name)"
                )
            return read_mask(mp, shape), mp
        mp = find_file(obj_dir, f.name)
        if mp is None:
            raise FileNotFoundError(
                f"object mask for {f} not found in {obj_dir} (expected {obj_dir / f.name})"
            )
        return read_mask(mp, shape), mp

    def split(n: int) -> tuple[list[bool], str]:
        return list(is_test_file), f"360-USID ({TEST_IMAGES}/ are the test views)"

    opts["n_test"] = None
    scene = _load_image_folder(full, "360-usid", split, mask_fn=mask_fn,
                               mask_dirs=[obj_dir] + ([tmask_dir] if tmask_dir else []), **opts)  # fmt: skip
    refs = list_images(root / REFERENCE) if (root / REFERENCE).is_dir() else []
    if refs:
        try:
            scene.ref_view = scene.index(refs[0].name)
        except (KeyError, ValueError, IndexError):
            log.warning(
                "%s: reference %s is not one of the views; the reference is chosen by rule", root, refs[0]
            )
    return scene
