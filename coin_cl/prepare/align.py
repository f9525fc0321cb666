"""How far recovered camera poses are from known ones: a similarity transform (scale, rotation,
translation: the gauge structure from motion cannot fix) fitted to the camera centres, then per-view
rotation and centre errors. Used by the tests and `benchmarks/prepare.py` to score `run_sfm`."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass
class PoseErrors:
    """Per view: rotation error (degrees) and camera-centre error (reference units) after the
    similarity alignment; scale of the fitted similarity (reference units per recovered unit)."""

    rot_deg: np.ndarray
    centre: np.ndarray
    scale: float

    @property
    def median_rot_deg(self) -> float:
        return float(np.median(self.rot_deg))

    @property
    def median_centre(self) -> float:
        return float(np.median(self.centre))


def rotation_angle_deg(d: np.ndarray) -> float:
    """Angle of a rotation (3, 3) in degrees; atan2 of sine and cosine keeps small angles exact."""
    s = 0.5 * np.linalg.norm([d[2, 1] - d[1, 2], d[0, 2] - d[2, 0], d[1, 0] - d[0, 1]])
    return float(np.degrees(np.arctan2(s, (np.trace(d) - 1) / 2)))


def pose_errors(est_viewmats: list[np.ndarray], ref_viewmats: list[np.ndarray]) -> PoseErrors:
    """Recovered vs reference world-to-camera matrices (4, 4), paired by position in the lists.

    The similarity ref_from_est is estimated on the camera centres (pycolmap's Umeyama); a rotation
    error is the angle of R_ref R_est_aligned^T."""
    import pycolmap

    if len(est_viewmats) != len(ref_viewmats) or len(est_viewmats) < 3:
        raise ValueError(
            f"pose_errors needs 3 or more paired views, got {len(est_viewmats)} and {len(ref_viewmats)}"
        )
    E = [np.asarray(v, np.float64) for v in est_viewmats]
    R = [np.asarray(v, np.float64) for v in ref_viewmats]
    ce = np.array([-v[:3, :3].T @ v[:3, 3] for v in E])
    cr = np.array([-v[:3, :3].T @ v[:3, 3] for v in R])
    sim = pycolmap.estimate_sim3d(ce, cr)
    if sim is None:
        raise ValueError("pose_errors: the camera centres are degenerate (collinear or identical)")
    M = np.asarray(sim.matrix())  # (3, 4) = [s R | t]
    s = float(sim.scale)
    Rs = M[:, :3] / s
    rot, cen = [], []
    for e, r, c_e, c_r in zip(E, R, ce, cr, strict=True):
        # world_ref = s Rs world_est + t, so the aligned rotation is R_est Rs^T.
        d = r[:3, :3] @ (e[:3, :3] @ Rs.T).T
        rot.append(rotation_angle_deg(d))
        cen.append(np.linalg.norm(M[:, :3] @ c_e + M[:, 3] - c_r))
    return PoseErrors(np.array(rot), np.array(cen), s)


def relative_rotation_errors(est_viewmats: list[np.ndarray], ref_viewmats: list[np.ndarray]) -> np.ndarray:
    """Gauge-free rotation errors: for every pair of views, the angle (degrees) between the
    recovered and the reference relative rotation R_i R_j^T. (n (n - 1) / 2,)."""
    E = [np.asarray(v, np.float64)[:3, :3] for v in est_viewmats]
    R = [np.asarray(v, np.float64)[:3, :3] for v in ref_viewmats]
    n = len(E)
    return np.array([rotation_angle_deg((E[i] @ E[j].T) @ (R[i] @ R[j].T).T)
                     for i in range(n) for j in range(i + 1, n)])  # fmt: skip
