"""Densification strategies: how the set of primitives grows and shrinks during training.

A strategy is a dataclass whose fields are its documented settings (gsplat's `strategy/`
pattern), kept outside the models: a model holds parameters and renders; the strategy watches
each training render and edits the model's rows through its `ParamOptimizer` (values and Adam
moments together). The trainer calls, per step:

    out = model.render(...)
    strategy.step_pre_backward(model, step, out)    # before loss.backward()
    ... loss.backward(); model.optimizer.step(step) ...
    events = strategy.step_post_backward(model, step, out)   # statistics, then row surgery

`initialize(model, seed)` binds a strategy to a model (allocates its statistics, seeds its
generator); `state_dict` / `load_state_dict` carry settings, statistics and generator through a
checkpoint. Steps are counted from 0; the schedules are in completed iterations (step + 1), so
"every 100" means after the 100th, 200th, ... step, as in 3DGS and Scaffold-GS.

- `Strategy`: the base, and a fixed set of primitives (no densification);
- `DefaultStrategy`: vanilla 3DGS clone / split / prune / opacity reset (gsplat's default);
- `ScaffoldStrategy`: Scaffold-GS anchor growing and pruning.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass, fields
from typing import TYPE_CHECKING, Any

import numpy as np
import torch
from torch import Tensor

from coin_cl.engine.geometry import quat_to_rotmat
from coin_cl.gs.base import RenderOutput, inverse_sigmoid, ndc_grad_norm
from coin_cl.gs.gaussians import PER_GAUSSIAN
from coin_cl.gs.scaffold import GRID_HALF_CELLS, PER_ANCHOR

if TYPE_CHECKING:
    from coin_cl.gs.base import Model
    from coin_cl.gs.gaussians import GaussianModel
    from coin_cl.gs.scaffold import ScaffoldModel

log = logging.getLogger(__name__)

_KEY_BITS = 21  # grid-coordinate hashing: each axis must fit in +-2^20 cells (scaffold.GRID_HALF_CELLS)


class Strategy:
    """Base strategy: keeps the primitives fixed. Subclasses are dataclasses of settings."""

    # Names of the statistics tensors `state_dict` saves (attributes of the strategy).
    _stats: tuple[str, ...] = ()

    def check_sanity(self, model: Model) -> None:
        """Raise if `model` lacks the parameters this strategy edits."""

    def initialize(self, model: Model, seed: int = 0, train_pixels: int = 0) -> None:
        """Bind to `model`: check it, allocate statistics sized to its rows, seed the generator
        that draws split positions / growth candidates. `train_pixels`: the pixels of all training
        views together (the trainer passes them), for a size cap tied to what the images can show
        (`ScaffoldStrategy.gaussians_per_pixel`); 0: unknown, no such cap."""
        self.check_sanity(model)
        self.train_pixels = int(train_pixels)
        self.gen = torch.Generator().manual_seed(seed)
        self._cap_logged = False  # the cap's log line is said once per run
        self._reset_stats(model)

    def size_limit(self, model: Model) -> dict[str, Any]:
        """The most primitives growth may reach and why ({} when growth is unbounded)."""
        return {}

    def _reset_stats(self, model: Model) -> None:
        pass

    def step_pre_backward(self, model: Model, step: int, out: RenderOutput) -> None:
        """Before backward: keep the screen-space gradient the statistics need."""
        m2d = out.meta.get("means2d")
        if m2d is not None and m2d.requires_grad:
            m2d.retain_grad()

    def step_post_backward(self, model: Model, step: int, out: RenderOutput) -> dict[str, int]:
        """After the optimiser step of `step`: gather statistics from `out`, then densify /
        prune; returns counts of what changed (all zero when nothing did)."""
        return {}

    def config(self) -> dict[str, Any]:
        return asdict(self) if hasattr(self, "__dataclass_fields__") else {}

    def state_dict(self) -> dict[str, Any]:
        return {
            "kind": type(self).__name__,
            "config": self.config(),
            "stats": {k: getattr(self, k) for k in self._stats},
            "gen": self.gen.get_state() if hasattr(self, "gen") else None,
        }

    def load_state_dict(self, sd: dict[str, Any]) -> None:
        """Restore settings, statistics and generator. Like a model's config, the checkpoint's
        settings win over the ones this object was built with (a resumed run keeps its schedule);
        keys this strategy does not know are ignored (older checkpoints)."""
        if sd.get("kind", type(self).__name__) != type(self).__name__:
            raise ValueError(f"checkpoint holds {sd['kind']} state, not {type(self).__name__}'s")
        known = {f.name for f in fields(self)} if hasattr(self, "__dataclass_fields__") else set()
        for k, v in (sd.get("config") or {}).items():
            if k in known:
                setattr(self, k, v)
        for k, v in sd.get("stats", {}).items():
            if k in self._stats:
                setattr(self, k, v.clone())
        if sd.get("gen") is not None:
            if not hasattr(self, "gen"):
                self.gen = torch.Generator()
            self.gen.set_state(sd["gen"])


@dataclass
class DefaultStrategy(Strategy):
    """Vanilla 3DGS densification (gsplat `DefaultStrategy` defaults).

    Every `refine_every` steps between `refine_start` and `refine_stop`, Gaussians whose mean
    NDC screen gradient exceeds `grow_grad2d` are cloned (if small in 3D) or split into two (if
    large); low-opacity and (after the first opacity reset) very large Gaussians are pruned; every
    `reset_every` steps opacities are clamped to twice the prune threshold. Screen gradients in NDC
    units (see `coin_cl.gs.base`: the pixel-position gradient times half the image size); 3D sizes
    in multiples of the model's scene `extent`; screen sizes in pixels. Growth never takes the
    model past `max_gaussians`: when more qualify than it leaves room for, the steepest grow.

    Statistics: grad2d [N] (summed NDC gradient norms), count [N] (renders where visible),
    max_radii [N] (largest screen radius, px).
    """

    prune_opa: float = 0.005  # prune when opacity falls below
    grow_grad2d: float = 0.0002  # mean NDC screen-gradient norm to grow (clone or split)
    grow_scale3d: float = 0.01  # x scene extent: at most this large => clone, else split
    prune_scale3d: float = 0.1  # x scene extent: larger => prune (after the first reset)
    prune_radius_px: float = 0.0  # > 0: also prune splats whose 3-sigma radius exceeded this (px)
    refine_start: int = 500
    refine_stop: int = 15_000
    refine_every: int = 100
    reset_every: int = 3000
    split_factor: float = 1.6  # children of a split get scale / 1.6 (3DGS)
    max_gaussians: int = 3_000_000  # growth never passes this (memory guard; a caller may lower it)

    _stats = ("grad2d", "count", "max_radii")

    def check_sanity(self, model: Model) -> None:
        missing = [k for k in PER_GAUSSIAN if k not in model.optimizer.params]
        if missing or not hasattr(model, "extent"):
            raise ValueError(f"DefaultStrategy needs a 3DGS model; {model.kind!r} lacks {missing}")

    def _reset_stats(self, model: Model) -> None:
        n = model.n_primitives
        self.grad2d = torch.zeros(n)
        self.count = torch.zeros(n)
        self.max_radii = torch.zeros(n)

    def step_post_backward(self, model: Model, step: int, out: RenderOutput) -> dict[str, int]:
        if step < self.refine_stop:
            self.update_stats(out)
        return self.refine(model, step)

    def update_stats(self, out: RenderOutput) -> None:
        """Accumulate the screen gradients of the Gaussians visible in `out`."""
        m = out.meta
        vis = m["radii"] > 0
        g = ndc_grad_norm(m["means2d"], m["width"], m["height"])
        self.grad2d[vis] += g[vis].to(self.grad2d.dtype)
        self.count[vis] += 1
        self.max_radii[vis] = torch.maximum(self.max_radii[vis], m["radii"][vis].float())

    def refine(self, model: GaussianModel, step: int) -> dict[str, int]:
        """Grow, prune and reset as scheduled after `step` (counted from 0)."""
        s = step + 1
        out = {"cloned": 0, "split": 0, "pruned": 0, "reset": 0}
        if s >= self.refine_stop:
            return out
        if s > self.refine_start and s % self.refine_every == 0:
            out["cloned"], out["split"] = self._grow(model)
            out["pruned"] = self._prune(model, s)
            self._reset_stats(model)
        if s % self.reset_every == 0:
            self._reset_opacity(model)
            out["reset"] = 1
        return out

    def _keep_stats(self, keep: Tensor, n_new: int = 0) -> None:
        """Keep the rows where `keep` [N] is True, then append `n_new` zero rows."""
        for name in self._stats:
            v = getattr(self, name)[keep]
            setattr(self, name, torch.cat([v, v.new_zeros(n_new)]))

    def _grow(self, model: GaussianModel) -> tuple[int, int]:
        p = model.optimizer.params
        if model.n_primitives >= self.max_gaussians:
            return 0, 0
        grads = self.grad2d / self.count.clamp_min(1)
        high = grads > self.grow_grad2d
        room = self.max_gaussians - model.n_primitives
        if int(high.sum()) > room:
            # A clone or a split adds one Gaussian each: grow the `room` steepest, so the cap is
            # met exactly and spent where the screen gradients say the fit is worst.
            keep = torch.topk(torch.where(high, grads, -1.0), room).indices
            high = torch.zeros_like(high)
            high[keep] = True
        small = torch.exp(p["scales"].data).amax(-1) <= self.grow_scale3d * model.extent
        dup = high & small
        split = high & ~small
        n_dup, n_split = int(dup.sum()), int(split.sum())
        if n_dup:
            model.optimizer.append_rows({k: p[k].data[dup] for k in PER_GAUSSIAN})
            # Clones inherit their parents' statistics (gsplat), unlike split children.
            for name in self._stats:
                v = getattr(self, name)
                setattr(self, name, torch.cat([v, v[dup]]))
            split = torch.cat([split, split.new_zeros(n_dup)])
        if n_split:
            self._split(model, split)
        return n_dup, n_split

    def _split(self, model: GaussianModel, mask: Tensor) -> None:
        """Replace each selected Gaussian with two, sampled from it, scales / split_factor."""
        p = {k: model.optimizer.params[k].data for k in PER_GAUSSIAN}
        scales = torch.exp(p["scales"][mask])
        R = quat_to_rotmat(p["quats"][mask])
        noise = torch.randn(2, *scales.shape, generator=self.gen)
        offs = torch.einsum("nij,bnj->bni", R, scales[None] * noise)
        new = {
            "means": (p["means"][mask][None] + offs).reshape(-1, 3),
            "scales": torch.log(scales / self.split_factor).repeat(2, 1),
        }
        for k in ("quats", "opacities", "sh0", "shN"):
            v = p[k][mask]
            new[k] = v.repeat(2, *([1] * (v.dim() - 1)))
        keep = ~mask
        model.optimizer.keep_rows(list(PER_GAUSSIAN), keep)
        model.optimizer.append_rows(new)
        self._keep_stats(keep, int(new["means"].shape[0]))

    def _prune(self, model: GaussianModel, s: int) -> int:
        p = model.optimizer.params
        prune = torch.sigmoid(p["opacities"].data) < self.prune_opa
        if s > self.reset_every:
            prune |= torch.exp(p["scales"].data).amax(-1) > self.prune_scale3d * model.extent
            if self.prune_radius_px > 0:
                prune |= self.max_radii > self.prune_radius_px
        n = int(prune.sum())
        if n:
            keep = ~prune
            model.optimizer.keep_rows(list(PER_GAUSSIAN), keep)
            self._keep_stats(keep)
        return n

    def _reset_opacity(self, model: GaussianModel) -> None:
        cap = float(inverse_sigmoid(self.prune_opa * 2.0))
        model.optimizer.set_rows("opacities", model.optimizer.params["opacities"].data.clamp_max(cap))


def neural_gaussian_cap(gaussians_per_pixel: float, train_pixels: int) -> int:
    """The most neural Gaussians a model may grow to: floor(gaussians_per_pixel x train_pixels),
    `train_pixels` the pixels of all training views together (sum of width x height); 0 when
    either is <= 0 (no cap)."""
    if gaussians_per_pixel <= 0 or train_pixels <= 0:
        return 0
    return int(gaussians_per_pixel * train_pixels)


def _grid_keys(coords: Tensor) -> Tensor:
    """[N, 3] int grid coordinates -> [N] int64 unique keys."""
    half = 1 << (_KEY_BITS - 1)
    assert half == GRID_HALF_CELLS
    if coords.numel() and (coords.abs().max() >= half):
        raise ValueError("anchor grid coordinates exceed +-2^20 cells: the voxel size is too small")
    c = coords.long() + half
    return (c[:, 0] << (2 * _KEY_BITS)) | (c[:, 1] << _KEY_BITS) | c[:, 2]


@dataclass
class ScaffoldStrategy(Strategy):
    """Scaffold-GS anchor growing and pruning (its `arguments/__init__.py`, 30k-step schedule).

    Between `start_stat` and `update_until` every training render adds to per-anchor opacity
    statistics and per-offset screen-gradient statistics (Scaffold-GS `training_statis`). Every
    `update_interval` steps after `update_from`, new anchors grow in empty voxels (at
    `update_depth` levels) where offsets had large gradients, and anchors whose Gaussians stayed
    nearly transparent are pruned (`adjust_anchor`).

    Growth is capped by what the images can show: the model's neural Gaussians (anchors x k
    offsets, `ScaffoldModel.n_primitives`) stay at most `neural_gaussian_cap(gaussians_per_pixel,
    train_pixels)` (and anchors at most `max_anchors`). When more new anchors qualify than the cap
    leaves room for, those whose offsets had the steepest screen gradients grow; the first time
    the cap holds growth back the log says so once, with the count and its reason. The cap bounds
    growth only: a model built above it (dense SfM points) keeps its anchors and grows only to
    `min_cap`, the floor a caller may set (Ref-GS: a multiple of its initial size).

    Statistics: opacity_accum [A], anchor_denom [A], offset_grad_accum [A*k], offset_denom [A*k]
    (k offsets per anchor).
    """

    start_stat: int = 500
    update_from: int = 1500
    update_interval: int = 100
    update_until: int = 15_000
    grad_threshold: float = 0.0002  # NDC screen-gradient units (see coin_cl.gs.base)
    min_opacity: float = 0.005
    success_threshold: float = 0.8
    update_depth: int = 3
    update_init_factor: int = 16
    update_hierarchy_factor: int = 4
    max_anchors: int = 1_000_000  # growth stops here (memory guard)
    # Neural Gaussians (anchors x k offsets) per training pixel (the pixels of all training views
    # together) that growth may reach; <= 0: no such cap. A late step's cost grows with the model,
    # so this also bounds how much slower late steps get. 0.02: on a real capture's Ref-GS (56
    # views, 6.7 M pixels, 53 k neural Gaussians from SfM) it held the test views' PSNR of no cap
    # (within 0.15 dB) at 600 steps, where 0.01 lost 0.6 dB, and stops the growth that took
    # longer runs to 0.03-0.04 per pixel (docs/BENCHMARKS.md, "Growth cap"). A model built above
    # it grows only to `min_cap` (SPIn-NeRF scene 1 starts at 0.11 per pixel).
    gaussians_per_pixel: float = 0.02
    # Growth may reach at least this many neural Gaussians whatever `gaussians_per_pixel` gives
    # (Ref-GS sets it from the model's initial size, `RefGSConfig.growth_over_initial`); 0: no floor.
    # No effect without the per-pixel cap (`max_anchors` alone bounds growth then).
    min_cap: int = 0

    _stats = ("opacity_accum", "anchor_denom", "offset_grad_accum", "offset_denom")

    def check_sanity(self, model: Model) -> None:
        missing = [k for k in PER_ANCHOR if k not in model.optimizer.params]
        if missing or not hasattr(model, "voxel_size"):
            raise ValueError(f"ScaffoldStrategy needs an anchor model; {model.kind!r} lacks {missing}")

    def _reset_stats(self, model: Model) -> None:
        a, k = model.n_anchors, model.cfg.n_offsets
        self.opacity_accum = torch.zeros(a)
        self.anchor_denom = torch.zeros(a)
        self.offset_grad_accum = torch.zeros(a * k)
        self.offset_denom = torch.zeros(a * k)

    def size_limit(self, model: Model) -> dict[str, Any]:
        """{'anchors': the most anchors growth may reach, 'neural_gaussians': that x k,
        'reason': why (the per-pixel cap, the caller's floor `min_cap` above it, or `max_anchors`)}."""
        k = model.cfg.n_offsets
        per_pixel = neural_gaussian_cap(self.gaussians_per_pixel, getattr(self, "train_pixels", 0))
        cap = max(per_pixel, self.min_cap) if per_pixel else 0
        if cap and cap // k < self.max_anchors:
            reason = (f"cap {per_pixel} = {self.gaussians_per_pixel:g} per training pixel x "
                      f"{self.train_pixels} pixels")  # fmt: skip
            if cap > per_pixel:
                reason = f"cap {cap} (the caller's floor, min_cap) over the per-pixel {reason}"
            return {"anchors": cap // k, "neural_gaussians": cap // k * k, "reason": reason}
        reason = f"max_anchors {self.max_anchors} (memory guard)"
        return {"anchors": self.max_anchors, "neural_gaussians": self.max_anchors * k, "reason": reason}

    def step_post_backward(self, model: Model, step: int, out: RenderOutput) -> dict[str, int]:
        s = step + 1
        if self.start_stat < s < self.update_until:
            self.update_stats(model, out)
        if s > self.update_from and s % self.update_interval == 0 and s < self.update_until:
            return self.adjust_anchors(model)
        return {"grown": 0, "pruned": 0, "held_back": 0}

    def update_stats(self, model: ScaffoldModel, out: RenderOutput) -> None:
        """Scaffold-GS `training_statis` for one render."""
        m, k = out.meta, model.cfg.n_offsets
        vis = m["anchor_visible"]
        op = m["neural_opacity"].clamp_min(0).view(-1, k)
        self.opacity_accum[vis] += op.sum(1)
        self.anchor_denom[vis] += 1
        # Map drawn Gaussians back to their (anchor, offset) slot.
        slot = torch.zeros(model.n_anchors * k, dtype=torch.bool)
        slot[vis.repeat_interleave(k)] = m["selected"]
        idx = slot.nonzero().squeeze(1)
        drawn = m["radii"] > 0
        g = ndc_grad_norm(m["means2d"], m["width"], m["height"])
        self.offset_grad_accum[idx[drawn]] += g[drawn].to(self.offset_grad_accum.dtype)
        self.offset_denom[idx[drawn]] += 1

    def adjust_anchors(self, model: ScaffoldModel) -> dict[str, int]:
        """Grow anchors from high-gradient offsets, then prune transparent anchors (Scaffold-GS
        `adjust_anchor`). Returns {'grown': n, 'pruned': n, 'held_back': n}, the last the new
        anchors the size cap kept from growing."""
        k = model.cfg.n_offsets
        grads = self.offset_grad_accum / self.offset_denom
        grads = torch.nan_to_num(grads, nan=0.0)
        offset_mask = self.offset_denom > self.update_interval * self.success_threshold * 0.5
        grown, held_back = self._grow(model, grads, offset_mask)
        # Reset statistics of the offsets that were considered; pad for the new anchors.
        self.offset_denom[offset_mask] = 0
        self.offset_grad_accum[offset_mask] = 0
        pad = model.n_anchors * k - self.offset_denom.shape[0]
        self.offset_denom = torch.cat([self.offset_denom, torch.zeros(pad)])
        self.offset_grad_accum = torch.cat([self.offset_grad_accum, torch.zeros(pad)])
        # Prune anchors seen often enough whose Gaussians stayed nearly transparent.
        prune = self.opacity_accum < self.min_opacity * self.anchor_denom
        checked = self.anchor_denom > self.update_interval * self.success_threshold
        prune &= checked
        self.opacity_accum[checked] = 0
        self.anchor_denom[checked] = 0
        n_prune = int(prune.sum())
        if n_prune:
            keep = ~prune
            model.optimizer.keep_rows(list(PER_ANCHOR), keep)
            self.opacity_accum = self.opacity_accum[keep]
            self.anchor_denom = self.anchor_denom[keep]
            kk = keep.repeat_interleave(k)
            self.offset_denom = self.offset_denom[kk]
            self.offset_grad_accum = self.offset_grad_accum[kk]
        return {"grown": grown, "pruned": n_prune, "held_back": held_back}

    def _grow(self, model: ScaffoldModel, grads: Tensor, offset_mask: Tensor) -> tuple[int, int]:
        """Grow new anchors; returns (anchors grown, new anchors the size cap held back)."""
        k, feat_dim = model.cfg.n_offsets, model.cfg.feat_dim
        init_len = model.n_anchors * k
        limit = self.size_limit(model)
        total = held_back = 0
        for i in range(self.update_depth):
            thr = self.grad_threshold * ((self.update_hierarchy_factor // 2) ** i)
            cand = (grads >= thr) & offset_mask
            cand &= torch.rand(cand.shape, generator=self.gen) > 0.5 ** (i + 1)
            inc = model.n_anchors * k - init_len
            if inc == 0 and i > 0:
                continue  # Scaffold-GS only descends a level after the previous one grew
            cand = torch.cat([cand, torch.zeros(inc, dtype=torch.bool)])
            p = {n: model.optimizer.params[n].data for n in PER_ANCHOR}
            scaling = torch.exp(p["scaling"])
            all_xyz = p["anchors"][:, None] + p["offsets"] * scaling[:, None, :3]
            size = model.voxel_size * (self.update_init_factor // (self.update_hierarchy_factor**i))
            sel_xyz = all_xyz.reshape(-1, 3)[cand]
            if sel_xyz.shape[0] == 0:
                continue
            sel_keys = _grid_keys(torch.round(sel_xyz / size))
            uniq, inv = torch.unique(sel_keys, return_inverse=True)
            occupied = torch.isin(uniq, _grid_keys(torch.round(p["anchors"] / size)))
            new_keep = ~occupied
            if not bool(new_keep.any()):
                continue
            room = max(0, limit["anchors"] - model.n_anchors)
            n_want = int(new_keep.sum())
            if n_want > room:
                # Over the cap: the new cells whose offsets had the steepest screen gradients grow
                # (the fit is worst there), kept in key order so the result is deterministic.
                g_sel = torch.cat([grads, grads.new_zeros(inc)])[cand]
                cell_g = torch.full((uniq.shape[0],), -torch.inf).scatter_reduce(
                    0, inv, g_sel.to(torch.float32), reduce="amax", include_self=False
                )
                best = torch.topk(torch.where(new_keep, cell_g, -torch.inf), room).indices
                new_keep = torch.zeros_like(new_keep)
                new_keep[best] = True
                held_back += n_want - room
                if room == 0:
                    continue
            # Recover the integer cell of each unique key from one of its members.
            first = torch.full((uniq.shape[0],), sel_keys.shape[0], dtype=torch.long)
            first.scatter_reduce_(0, inv, torch.arange(sel_keys.shape[0]), reduce="amin")
            cells = torch.round(sel_xyz[first] / size)
            new_anchor = (cells * size)[new_keep].float()
            feat_rep = p["features"].repeat_interleave(k, 0)[cand]
            feat = torch.full((uniq.shape[0], feat_dim), -torch.inf)
            feat = feat.scatter_reduce(
                0, inv[:, None].expand(-1, feat_dim), feat_rep, reduce="amax", include_self=False
            )[new_keep]
            n_new = new_anchor.shape[0]
            model.optimizer.append_rows(
                {
                    "anchors": new_anchor,
                    "offsets": torch.zeros(n_new, k, 3),
                    "features": feat,
                    "scaling": torch.full((n_new, 6), float(np.log(size))),
                }
            )
            self.opacity_accum = torch.cat([self.opacity_accum, torch.zeros(n_new)])
            self.anchor_denom = torch.cat([self.anchor_denom, torch.zeros(n_new)])
            total += n_new
        if held_back and not self._cap_logged:
            self._cap_logged = True
            above = model.n_anchors > limit["anchors"]
            log.info("anchor growth held at %d anchors (%d neural Gaussians): %s; %d new anchors "
                     "not grown (%s)", model.n_anchors, model.n_primitives, limit["reason"], held_back,
                     "the model starts above the cap, so it does not grow" if above else
                     "the steepest-gradient ones grow first, and again as pruning frees room")  # fmt: skip
        return total, held_back


STRATEGIES: dict[str, type[Strategy]] = {"3dgs": DefaultStrategy, "scaffold": ScaffoldStrategy}


def default_strategy(kind: str) -> Strategy:
    """The published densification for a model kind ('3dgs' or 'scaffold')."""
    if kind not in STRATEGIES:
        raise ValueError(f"no default strategy for model {kind!r}: use one of {tuple(STRATEGIES)}")
    return STRATEGIES[kind]()
