"""`load_scene`: one entry point for SPIn-NeRF folders (and GScream's / FreeInpaint's copies of
them), plain COLMAP folders, nerfstudio folders and our own scenes; a small dispatcher over the
per-layout loaders.

Layouts (docs/SCENES.md has the user-facing version):
- a folder with `scene.json` is one written by `save_scene` (coin-cl's own format): `native.py`;
- a folder with `transforms.json` is a nerfstudio folder: `nerfstudio.py`;
- a folder with `test_images/` and `object_masks/` is 360-USID: `usid.py`;
- a folder whose image folder has `label/`, `test_label/` or `mask_test/`, or with `lama_input/` or
  `poses_bounds.npy`, is SPIn-NeRF / LLFF; any other image folder is plain COLMAP: both in `folder.py`.
Folder rules:
- images: `images_4/` if present, else `images/`, else the first `images_N/`;
- poses: `sparse/0` (or `sparse/`, or the folder itself) with images.bin/.txt, else LLFF
  `poses_bounds.npy` (row i = view i of `views.txt`, or of the sorted image names when all are present);
- split: `views.txt` split column, else `sparse/0/test.txt`, else the first `n_test` names by sort
  order in the SPIn-NeRF layout (40) and none in a plain COLMAP folder;
- masks: `<images>/label/<name>` for training views, `<images>/test_label/out_{k+1:05d}.png` for test
  view k (SPIn-NeRF); `lama_input/<stem>_mask.png` and `<images>/mask_test/<stem>.png` (GScream /
  FreeInpaint); or `masks/<name>` in a plain COLMAP folder. Masks present but all empty: an error.
"""

from __future__ import annotations

from pathlib import Path

from .folder import LAMA_INPUT, image_dir, load_colmap_folder, load_spinnerf_folder, open_folder
from .io import image_header, list_images
from .native import load_native_folder, save_scene
from .nerfstudio import TRANSFORMS, load_nerfstudio_folder
from .types import Scene
from .usid import is_usid, load_usid_folder

__all__ = ["LAYOUTS", "detect_layout", "image_sizes", "load_scene", "save_scene"]

# layout name -> loader of an image folder (the native format has no image-folder step)
LAYOUTS = {"spinnerf": load_spinnerf_folder, "colmap": load_colmap_folder, "360-usid": load_usid_folder}


def detect_layout(root: Path, imgdir: Path) -> str:
    """The layout name: "360-usid" when the root has test_images/ and object_masks/; "spinnerf"
    when the image folder has label/, test_label/ or mask_test/, or the root has lama_input/
    (GScream / FreeInpaint) or poses_bounds.npy; else "colmap"."""
    if is_usid(root):
        return "360-usid"
    spinnerf = (
        (imgdir / "label").is_dir()
        or (imgdir / "test_label").is_dir()
        or (imgdir / "mask_test").is_dir()
        or (root / LAMA_INPUT).is_dir()
        or (root / "poses_bounds.npy").is_file()
    )
    return "spinnerf" if spinnerf else "colmap"


def load_scene(
    path: str | Path,
    *,
    images: str | None = None,
    resolution: float = 1.0,
    undistort: bool | None = None,
    n_test: int | None = None,
    mask_dilate: int = 0,
    priors: bool = True,
) -> Scene:
    """Load a scene folder (SPIn-NeRF layout, plain COLMAP, nerfstudio, or one written by `save_scene`).

    images: image folder name inside `path` (default: images_4, images, images_N).
    resolution: further downscale (0.5 -> half size); K is scaled to match.
    undistort: undo lens distortion of COLMAP models with OpenCV. Default: yes for poses from a
      COLMAP model; no for LLFF poses_bounds.npy (SPIn-NeRF/LLFF loaders ignore it too).
    n_test: treat the first n_test views by name as test views (overrides the folder's split).
    mask_dilate: dilate training masks this many iterations with a 5x5 kernel (SPIn-NeRF uses 5).
    priors: load RGB_inpainted/ and Depth_inpainted/ when present.
    """
    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f"scene folder {root} not found")
    if (root / "scene.json").is_file():
        return load_native_folder(root).resized(resolution)
    if (root / TRANSFORMS).is_file():
        return load_nerfstudio_folder(
            root, undistort=undistort, n_test=n_test, mask_dilate=mask_dilate, priors=priors
        ).resized(resolution)
    imgdir = image_dir(root, images)
    files = list_images(imgdir)
    if not files:
        raise FileNotFoundError(f"no .png/.jpg images in {imgdir}")
    loader = LAYOUTS[detect_layout(root, imgdir)]
    scene = loader(
        open_folder(root, imgdir, files),
        undistort=undistort,
        n_test=n_test,
        mask_dilate=mask_dilate,
        priors=priors,
    )
    return scene.resized(resolution)


def image_sizes(path: str | Path, *, images: str | None = None) -> list[tuple[Path, int, int]]:
    """[(file, width, height)] of every view image `load_scene(path, images=images)` would decode,
    from the files' headers alone (`scene.io.image_header`: nothing decoded; a header declaring
    more than `io.MAX_IMAGE_PIXELS` is a ValueError naming the file). What a memory estimate made
    before loading reads."""
    from coin_cl.schema import SCENE, inside, parse

    root = Path(path)
    if not root.is_dir():
        raise FileNotFoundError(f"scene folder {root} not found")
    if (root / "scene.json").is_file():
        sj = root / "scene.json"
        doc = parse(sj, SCENE, "re-create it with save_scene")
        files = [inside(root, v["image"], sj, f"views[{i}].image") for i, v in enumerate(doc["views"])]
    else:
        imgdir = image_dir(root, images)
        files = list_images(imgdir)
    return [(f, *image_header(f)[:2]) for f in files]
