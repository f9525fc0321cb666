"""Gradient-domain (Poisson) blending: paste the texture of one image into a region of another so
that its colours meet the surroundings without a seam (Perez, Gangnet and Blake, *Poisson Image
Editing*, SIGGRAPH 2003).

Inside `region` the result f solves the screened Poisson equation

    sum_{q in N(p)} (f_p - f_q) + eps (f_p - guide_p) = sum_{q in N(p)} v_pq,   p in region,

over the 4-neighbours N(p) inside the image, with f_q = base_q for q outside the region (Dirichlet:
the surroundings stay as they are) and no term for neighbours beyond the image's border (Neumann: a
region that touches the border is continued, not pinned to an invented value). The guidance v_pq is
the guide's own gradient guide_p - guide_q where p and q carry the same label (one source), and 0
where the labels differ: a step between two sources, or between the pasted source and the
surroundings, is not carried into the result, so the result is the guide's texture on colours that
follow the surroundings. The tiny screening term eps (`EPS`) keeps the system solvable for a region with no
pixel outside it (a full mask, or a component cut off by the image's border on every side): there
the result is the guide itself, shifted by nothing. scipy's sparse LU solves the system once for the
three channels. `screened_solve` is that solver on its own, also without guidance and with no
coupling across labels (the per-surface colour of `surface_chroma`).

Images are (H, W, C) float in [0, 1]; the region (H, W) bool. Pixels outside the region are
bit-identical to `base`.
"""

from __future__ import annotations

import numpy as np

# The screening weight: far below the Laplacian's 4 (0.0015 off across a 200 px hole), enough to make
# a region without boundary solvable.
EPS = 1e-6


def poisson_blend(
    base: np.ndarray, guide: np.ndarray, region: np.ndarray, labels: np.ndarray | None = None
) -> np.ndarray:
    """The guide's texture blended into `base` inside `region` (the module docstring's equation).

    Args:
        base: [H, W, C] the image whose pixels outside `region` are kept and bound the solution.
        guide: [H, W, C] whose gradients inside the region are kept (where labels agree).
        region: [H, W] bool, the pixels solved for.
        labels: [H, W] int, the source of each guide pixel; a gradient between two pixels of
            different labels is not carried. None: one source everywhere (classic Poisson editing,
            the guide's gradient also across the region's edge).
    Returns:
        [H, W, C] float32, clipped to [0, 1]; `base` where the region is empty.
    Raises:
        ValueError: shapes that disagree, or non-finite values where they are read.
    """
    base = np.asarray(base, np.float64)
    guide = np.asarray(guide, np.float64)
    region = np.asarray(region, bool)
    if base.shape != guide.shape or base.ndim != 3 or base.shape[:2] != region.shape:
        raise ValueError(f"poisson_blend: base {base.shape}, guide {guide.shape} and region {region.shape} "
                         "must be (H, W, C), (H, W, C) and (H, W)")  # fmt: skip
    if labels is None:
        labels = np.zeros(region.shape, np.int64)
    labels = np.asarray(labels)
    if labels.shape != region.shape:
        raise ValueError(f"poisson_blend: labels {labels.shape} must match the region {region.shape}")
    if not region.any():
        return base.astype(np.float32)
    if not np.isfinite(guide[region]).all():
        raise ValueError("poisson_blend: the guide is not finite inside the region")
    out = screened_solve(base, region, target=guide, guide=guide, labels=labels)
    return np.clip(out, 0.0, 1.0).astype(np.float32)


def screened_solve(
    base: np.ndarray,
    region: np.ndarray,
    target: np.ndarray,
    guide: np.ndarray | None = None,
    labels: np.ndarray | None = None,
    cut: bool = False,
    screen: float = EPS,
) -> np.ndarray:
    """The screened equation of the module docstring, solved inside `region` and returned unclipped.

    Args:
        base: [H, W, C] the values outside the region (the boundary), kept as they are.
        region: [H, W] bool, the pixels solved for (not empty).
        target: [H, W, C] the screening term's target inside the region.
        guide: [H, W, C] whose gradients are carried between same-label pixels; None: no guidance
            (a screened Laplace equation: the smoothest surface through the boundary values).
        labels: [H, W] int; None: one label everywhere.
        cut: neighbours of different labels are not coupled at all (no flux across a label's edge,
            the boundary values of another label unread), rather than coupled without guidance.
        screen: the screening weight, against the Laplacian's 1 per neighbour.
    Returns:
        [H, W, C] float64: `base` with the region's solution.
    Raises:
        ValueError: base not finite where the solution reads it.
    """
    from scipy.sparse import csc_matrix
    from scipy.sparse.linalg import splu

    base = np.asarray(base, np.float64)
    H, W, C = base.shape
    labels = np.zeros((H, W), np.int64) if labels is None else labels
    idx = -np.ones((H, W), np.int64)
    ys, xs = np.nonzero(region)
    n = len(ys)
    idx[ys, xs] = np.arange(n)
    diag = np.full(n, screen)
    rhs = screen * np.asarray(target, np.float64)[ys, xs]  # [n, C]
    rows, cols = [], []
    for dy, dx in ((-1, 0), (1, 0), (0, -1), (0, 1)):
        qy, qx = ys + dy, xs + dx
        inside = (qy >= 0) & (qy < H) & (qx >= 0) & (qx < W)  # beyond the border: no term (Neumann)
        p = np.nonzero(inside)[0]
        qy, qx = qy[p], qx[p]
        same = labels[ys[p], xs[p]] == labels[qy, qx]
        if cut:
            p, qy, qx, same = p[same], qy[same], qx[same], same[same]
        diag[p] += 1.0
        if guide is not None:
            rhs[p] += np.where(same[:, None], guide[ys[p], xs[p]] - guide[qy, qx], 0.0)
        q = idx[qy, qx]
        unknown = q >= 0
        rows.append(p[unknown])
        cols.append(q[unknown])
        fixed = ~unknown  # the neighbour is outside the region: its value is base's (Dirichlet)
        outside = base[qy[fixed], qx[fixed]]
        if not np.isfinite(outside).all():
            raise ValueError("poisson: base is not finite on the region's boundary")
        rhs[p[fixed]] += outside
    r = np.concatenate(rows + [np.arange(n)])
    c = np.concatenate(cols + [np.arange(n)])
    v = np.concatenate([-np.ones(len(r) - n), diag])
    f = splu(csc_matrix((v, (r, c)), shape=(n, n))).solve(rhs)
    out = base.copy()
    out[ys, xs] = f
    return out
