"""The report `run_sfm` writes (`SCENE/prepare_report.json` and `.txt`): which photos were posed,
the reprojection error, and why each dropped photo was dropped (read from the feature database)."""

from __future__ import annotations

import json
from dataclasses import asdict, dataclass, field
from pathlib import Path

from ..scene.io import write_text

REPORT = "prepare_report"


@dataclass
class SfmReport:
    """What `run_sfm` did: registered and dropped images (name -> reason), mean reprojection error
    (pixels, at the working size), point count, the matching used, the working size, the first
    photo's size, seconds per step, and the held-out photos localized in the model (name ->
    {matched_points, inliers}; test views, not in `registered`)."""

    n_photos: int
    registered: list[str]
    dropped: dict[str, str]
    mean_reproj_error: float
    n_points: int
    matching: str
    width: int
    height: int
    photo_width: int
    photo_height: int
    seconds: dict[str, float] = field(default_factory=dict)
    held_out: dict[str, dict[str, int]] = field(default_factory=dict)

    def text(self) -> str:
        lines = [
            f"registered {len(self.registered)} of {self.n_photos} photos "
            f"({self.width}x{self.height}, {self.matching} matching)",
            f"mean reprojection error {self.mean_reproj_error:.3f} px, {self.n_points} sparse points",
        ]
        if self.held_out:
            lines.append(f"held out (test views, localized, not trained on): {len(self.held_out)}")
            lines += [f"  {n}: {v['inliers']} of {v['matched_points']} matched points fit its pose"
                      for n, v in sorted(self.held_out.items())]  # fmt: skip
        if self.dropped:
            lines.append("dropped:")
            lines += [f"  {n}: {why}" for n, why in sorted(self.dropped.items())]
        lines.append("seconds: " + ", ".join(f"{k} {v:.1f}" for k, v in self.seconds.items()))
        return "\n".join(lines) + "\n"


def why_dropped(
    db_path: Path, names: list[str], registered: set[str], others: dict[str, int]
) -> dict[str, str]:
    """name -> reason for every image not in the kept model."""
    import pycolmap

    with pycolmap.Database.open(db_path) as db:
        images = {im.image_id: im.name for im in db.read_all_images()}
        n_kp = {im.name: db.num_keypoints_for_image(im.image_id) for im in db.read_all_images()}
        pair_ids, geoms = db.read_two_view_geometries()
    partners: dict[str, int] = {n: 0 for n in names}
    for pid, g in zip(pair_ids, geoms, strict=True):
        if len(g.inlier_matches) == 0:
            continue
        a, b = pycolmap.pair_id_to_image_pair(pid)
        for i in (a, b):
            partners[images[i]] = partners.get(images[i], 0) + 1
    out = {}
    for n in names:
        if n in registered:
            continue
        if n_kp.get(n, 0) == 0:
            out[n] = "no features found (blank, blurred or tiny image)"
        elif partners.get(n, 0) == 0:
            out[n] = "matched no other photo (not of this scene, or no overlap with the others)"
        elif n in others:
            out[n] = (
                f"registered only in a separate model of {others[n]} photos, disconnected from the "
                "main one; add photos between the two parts"
            )
        else:
            out[n] = (
                f"matched {partners[n]} photo(s) but the mapper could not place it (too few 3D points seen)"
            )
    return out


def write_report(scene: Path, report: SfmReport) -> None:
    write_text(scene / f"{REPORT}.json", json.dumps(asdict(report), indent=1))
    write_text(scene / f"{REPORT}.txt", report.text())


def read_report(scene: str | Path) -> SfmReport:
    return SfmReport(**json.loads((Path(scene) / f"{REPORT}.json").read_text()))
