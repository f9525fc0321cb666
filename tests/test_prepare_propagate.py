"""coin_cl.prepare.propagate / annotate / scene_masks: masks spread from one annotated view of the
synthetic room (exact cameras and masks) to the other training views."""

import numpy as np
import pytest

from coin_cl.prepare.annotate import box_mask, check_box, read_annotation, resolve_view, scribble_mask
from coin_cl.prepare.propagate import PropagateConfig, depth_range, iou, propagate_masks
from coin_cl.scene.io import write_png
from coin_cl.scene.masks import bbox

# IoU over the non-annotated training views. Measured on this room (12 views, 256x192), mean /
# worst: mask 0.952 / 0.827, box 0.949 / 0.828, scribble 0.949 / 0.827 (docs/PREPARE.md's floors
# on real data are 0.85 mean, 0.6 worst; here the worst floor is raised to 0.7).
FLOOR = {"mask": 0.85, "box": 0.85, "scribble": 0.85}
WORST = 0.7


@pytest.fixture(scope="module")
def room():
    from coin_cl.scene.synthetic import make_synthetic

    s = make_synthetic(coverage=180, n_views=16, width=256, height=192, supersample=1, n_points=8000)
    tr = [i for i in range(len(s.cameras)) if not s.is_test[i]]
    cams = [s.cameras[i] for i in tr]
    imgs = [s.present[i] for i in tr]
    gt = [s.masks[i] for i in tr]
    ref = int(np.argmax([m.sum() for m in gt]))
    return cams, imgs, gt, ref, s.points


def strokes_on(mask: np.ndarray) -> np.ndarray:
    """Two strokes a user would draw across the object: a cross through its centre, inside it."""
    import cv2

    inner = cv2.erode(mask.astype(np.uint8), np.ones((9, 9), np.uint8)).astype(bool)
    ys, xs = np.nonzero(inner)
    cy, cx = int(ys.mean()), int(xs.mean())
    canvas = np.zeros(mask.shape, np.uint8)
    cv2.line(canvas, (int(xs.min()), cy), (int(xs.max()), cy), 1, 3)
    cv2.line(canvas, (cx, int(ys.min())), (cx, int(ys.max())), 1, 3)
    return canvas.astype(bool) & inner


@pytest.mark.parametrize("kind", ["mask", "box", "scribble"])
def test_propagated_masks_match_the_truth(room, kind):
    cams, imgs, gt, ref, points = room
    if kind == "mask":
        m = gt[ref]
    elif kind == "box":
        y0, y1, x0, x1 = bbox(gt[ref])
        m = box_mask(imgs[ref], (x0 - 4, y0 - 4, x1 + 4, y1 + 4))
    else:
        m = scribble_mask(imgs[ref], strokes_on(gt[ref]))
    assert iou(m, gt[ref]) > 0.8  # the annotated view itself
    res = propagate_masks(cams, imgs, ref, m, points)
    ious = [iou(res.masks[v], gt[v]) for v in range(len(cams)) if v != ref]
    assert np.mean(ious) >= FLOOR[kind], np.round(ious, 3)
    assert min(ious) >= WORST, np.round(ious, 3)
    assert res.source[ref] == "annotation"


def test_segment_hook_is_used(room):
    cams, imgs, gt, ref, points = room
    calls = []

    def segment(image, prior, seeds, bg_seeds):  # a user's segmenter: here, the prior as is
        calls.append(prior.shape)
        return prior

    res = propagate_masks(cams, imgs, ref, gt[ref], points, segment=segment)
    assert len(calls) == 2 * (len(cams) - 1)  # first pass and consensus pass
    assert np.mean([iou(res.masks[v], gt[v]) for v in range(len(cams)) if v != ref]) > 0.6


def test_depth_range_takes_the_largest_cluster():
    z = np.concatenate([np.full(30, 2.0) + np.linspace(0, 0.1, 30), np.full(10, 5.0)])
    near, far, keep = depth_range(z, PropagateConfig(depth_pad=0.0, depth_percentiles=(0, 100)))
    assert keep.sum() == 30 and near == pytest.approx(2.0) and far == pytest.approx(2.1)


def test_too_few_points_is_an_error(room):
    cams, imgs, gt, ref, points = room
    with pytest.raises(ValueError, match="sparse points fall inside"):
        propagate_masks(cams, imgs, ref, gt[ref], points[:3])
    with pytest.raises(ValueError, match="empty"):
        propagate_masks(cams, imgs, ref, np.zeros_like(gt[ref]), points)


def test_box_outside_the_image():
    with pytest.raises(ValueError, match="outside view v.png \\(64x48"):
        check_box((70, 10, 90, 20), 64, 48, "v.png")
    with pytest.raises(ValueError, match="smaller than"):
        check_box((10, 10, 11, 30), 64, 48, "v.png")
    with pytest.raises(ValueError, match="4 numbers"):
        check_box((1, 2, 3), 64, 48, "v.png")
    assert check_box((-5, 10, 30, 60), 64, 48, "v.png") == (0, 10, 30, 48)  # overlapping: clipped


def test_annotation_images(tmp_path):
    m = np.zeros((96, 128), np.uint8)
    m[20:40, 30:60] = 255
    write_png(tmp_path / "big.png", m)
    small = read_annotation(tmp_path / "big.png", 64, 48)  # photo-size annotation, prepared view
    assert small.shape == (48, 64) and small[15, 20] and not small[5, 5]
    write_png(tmp_path / "tall.png", np.full((128, 96), 255, np.uint8))
    with pytest.raises(ValueError, match="tall.png is 96x128"):
        read_annotation(tmp_path / "tall.png", 64, 48)
    write_png(tmp_path / "empty.png", np.zeros((48, 64), np.uint8))
    with pytest.raises(ValueError, match="empty"):
        read_annotation(tmp_path / "empty.png", 64, 48)


def test_resolve_view():
    names = ["a.png", "b.png"]
    assert resolve_view("b", names) == 1 and resolve_view("b.jpg", names) == 1 and resolve_view(0, names) == 0
    with pytest.raises(ValueError, match="not a prepared view"):
        resolve_view("c", names)


def test_box_in_photo_pixels(room, tmp_path):
    """A box drawn on a photo twice the prepared size lands on the same object."""
    import cv2

    from coin_cl.prepare.scene_masks import Annotation, PreparedViews, reference_mask

    cams, imgs, gt, ref, points = room
    names = [c.name for c in cams]
    views = PreparedViews(names, cams, imgs, points, [np.zeros(0, np.int64)] * len(cams))
    write_png(tmp_path / names[ref].replace(".png", ".jpg"), cv2.resize(imgs[ref], (512, 384)))
    y0, y1, x0, x1 = bbox(gt[ref])
    box = (2 * (x0 - 4), 2 * (y0 - 4), 2 * (x1 + 4), 2 * (y1 + 4))
    k, m = reference_mask(views, Annotation(view=names[ref], box=box, photos_dir=tmp_path))
    assert k == ref and iou(m, gt[ref]) > 0.8
    with pytest.raises(ValueError, match="outside view"):  # the same box without the photo's scale
        reference_mask(views, Annotation(view=names[ref], box=(300, 200, 400, 300)))
    with pytest.raises(ValueError, match="exactly one"):
        Annotation(view=0, box=box, mask="m.png")
