"""The settings of an insertion from an edited reference view (`coin_cl.pipeline.insert` with the
masks' visual hull, `coin_cl.pipeline.insert_geometry` from one photo)."""

from __future__ import annotations

from dataclasses import dataclass

# The object's shape behind its silhouette (`InsertConfig.profile`).
PROFILES = ("extrude", "rounded", "revolve")


@dataclass
class InsertConfig:
    """edit_tol: a reference pixel is edited when a channel differs from the capture by more than
    this ([0, 1] units; 2/255 absorbs 8-bit round trips). hull_fraction: share of the seeing views
    whose mask must hold a point for it to be in the hull (0.9 tolerates masks a pixel short).
    min_views: views that must see a point for the hull to decide. hull_samples: depth samples per
    ray (then one refinement between the last outside and first inside sample, as many again).
    ref_match_tol: mean absolute difference outside the mask above which the edited image is not
    taken for a view of this scene. propagate: False = the naive alternative the benchmark scores
    against: no lift; the other views keep their captures (empty footprints), so a GS is simply
    trained on the edited reference beside the unedited views. With a text prompt, True: SD2 draws
    the reference alone and the lift (hull) carries it into the other views; False: SD2 on every
    view and CLG sampling with the prompt.

    The one-photo path (`coin_cl.pipeline.insert_geometry`, its module doc has the measurements):
    regions: where the object may appear in the other views. "hull": the scene's masks cover it
    in every view and the edit is lifted by their visual hull (the path above). "derive": only
    the edited photo is needed; the object is stood on the surface under it and every other view's
    region is its projection grown by `region_margin` px (the masks of every later stage; the
    scene's own masks are not used). "auto" (default): "hull" when every training view other than
    the edited one has a mask, else "derive". min_component: connected parts of the edit region
    under this share of the largest are dropped (stray retouches). surface_tol: RANSAC inlier
    distance of the surface fit, as a share of the depth there. contact: "columns" (a vertical
    front over the silhouette's contact curve) or "plane" (one billboard through the contacts).
    profile: "extrude" (constant thickness), "rounded" (thickness from the silhouette's distance
    transform) or "revolve" (a solid of revolution about the vertical: round objects; `thickness`
    and `contact` unused, `coin_cl.pipeline.insert_revolve`). thickness: the object's depth as a
    share of its width. region_margin: px the derived regions extend beyond the object's
    projection (None: 1 % of the view's longer side, at least 1). max_points: cap on lifted points
    (samples along the rays, or the shell's spacing, get coarser beyond it). occlusion: the
    scene's sparse points standing in front of the object hide it in a view (its region there
    leaves them out, so the captured scene stays in front of it; a visible part that shows little
    of the object's outline is a gap in the occluder's points and is hidden too,
    `insert_geometry.visible_footprint`); False: the object is drawn over everything it projects
    onto."""

    edit_tol: float = 2.0 / 255.0
    hull_fraction: float = 0.9
    min_views: int = 2
    hull_samples: int = 128
    ref_match_tol: float = 0.08
    propagate: bool = True
    regions: str = "auto"
    min_component: float = 0.05
    surface_tol: float = 0.01
    contact: str = "columns"
    profile: str = "revolve"
    thickness: float = 0.65
    region_margin: int | None = None
    max_points: int = 2_000_000
    occlusion: bool = True

    def __post_init__(self) -> None:
        for name, ok, what in (
            ("edit_tol", 0.0 <= self.edit_tol < 1.0, "in [0, 1)"),
            ("hull_fraction", 0.0 < self.hull_fraction <= 1.0, "in (0, 1]"),
            ("min_views", isinstance(self.min_views, int) and self.min_views >= 1, "an integer >= 1"),
            (
                "hull_samples",
                isinstance(self.hull_samples, int) and self.hull_samples >= 2,
                "an integer >= 2",
            ),
            ("ref_match_tol", self.ref_match_tol > 0, "> 0"),
            ("occlusion", isinstance(self.occlusion, bool), "True or False"),
            ("regions", self.regions in ("auto", "hull", "derive"), "'auto', 'hull' or 'derive'"),
            ("min_component", 0.0 <= self.min_component <= 1.0, "in [0, 1]"),
            ("surface_tol", 0.0 < self.surface_tol < 1.0, "in (0, 1)"),
            ("contact", self.contact in ("columns", "plane"), "'columns' or 'plane'"),
            ("profile", self.profile in PROFILES, "one of " + ", ".join(map(repr, PROFILES))),
            ("thickness", 0.0 <= self.thickness <= 10.0, "in [0, 10]"),
            (
                "region_margin",
                self.region_margin is None
                or (isinstance(self.region_margin, int) and self.region_margin >= 0),
                "an integer >= 0 or None",
            ),
            (
                "max_points",
                isinstance(self.max_points, int) and self.max_points >= 1000,
                "an integer >= 1000",
            ),
        ):
            if not ok:
                raise ValueError(f"InsertConfig.{name} is {getattr(self, name)!r}: give {what}")
