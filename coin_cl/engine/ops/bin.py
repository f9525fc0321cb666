"""Tile binning (kernels/bin.cl): which splats each 16x16 tile composites, in depth order."""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import torch
from torch import Tensor

from coin_cl.engine import constants as cst
from coin_cl.engine.errors import PairOverflowError
from coin_cl.engine.ops._util import groups, i32
from coin_cl.engine.runtime import DeviceArray, Runtime, resolve_device


@dataclass
class TileBins:
    """Depth-ordered splat ids per tile, the input of every per-pixel pass.

    ids[tile_start[t]:tile_end[t]] are tile t's splats front to back (t = ty * tiles_x + tx);
    pair_slot[pair_start[g]:pair_start[g + 1]] says where splat g's pairs are in `ids` (the
    deterministic gradient reduction walks it); extents [N, 2] are the per-splat half extents (px)
    of the opacity-aware box, read by the rasterizers (negative: the splat reaches no pixel).
    """

    tiles_x: int
    tiles_y: int
    tile_start: Tensor  # [n_tiles] int32
    tile_end: Tensor  # [n_tiles] int32
    ids: Tensor  # [n_pairs] int32
    pair_start: Tensor  # [N + 1] int32
    pair_slot: Tensor  # [n_pairs] int32
    extents: Tensor  # [N, 2] float32
    n_pairs: int = 0
    n_visible: int = 0
    # Device buffers of the fields above, by runtime: every pass over the view reads them without
    # another copy on the discrete-memory path. The fields are never written after `bin_tiles`.
    buffers: dict = field(default_factory=dict, repr=False, compare=False)

    @property
    def n_tiles(self) -> int:
        return self.tiles_x * self.tiles_y

    def arrays(self, rt: Runtime, *names: str) -> list[DeviceArray]:
        """Device arrays of the named fields on `rt`, uploaded at the first use only."""
        out = []
        for name in names:
            hit = self.buffers.get((id(rt), name))
            if hit is None or hit[0] is not rt:  # (an id may be reused once a runtime is gone)
                hit = self.buffers[(id(rt), name)] = (rt, rt.array(getattr(self, name)).buf)
            out.append(rt.reuse(getattr(self, name), hit[1]))
        return out

    def keep(self, rt: Runtime, name: str, arr: DeviceArray) -> None:
        """Remember the buffer a kernel wrote field `name` into (after its launch finished)."""
        self.buffers[(id(rt), name)] = (rt, arr.buf)

    def tile(self, t: int) -> Tensor:
        """[k] int64: the ids of tile t, front to back."""
        return self.ids[int(self.tile_start[t]) : int(self.tile_end[t])].long()


def depth_keys(depths: Tensor) -> Tensor:
    """[N] int32 keys whose signed order is float32 `depths`' ascending order (IEEE-754 total
    order; -0.0 and +0.0 tie, every NaN sorts after +inf)."""
    d = torch.as_tensor(depths, dtype=torch.float32).flatten() + 0.0  # a copy; -0.0 -> +0.0 (they tie)
    d[torch.isnan(d)] = float("nan")  # one NaN pattern (sign bit clear), so every NaN sorts last
    bits = d.view(torch.int32)
    # Negative floats: flip the 31 bits below the sign (larger magnitude, smaller key).
    return torch.where(bits < 0, bits ^ 0x7FFFFFFF, bits)


def stable_depth_order(depths: Tensor, keep: Tensor | None = None) -> Tensor:
    """[K] int64: the indices of float32 `depths` [N] (only those where the bool mask `keep` [N]
    is set, when given) sorted by depth ascending, ties in index order (a stable argsort, NaN last).

    A stable sort of 32-bit integer keys (`depth_keys`): torch sorts those 2.6x faster than 64-bit
    keys with the index in their low bits and 10x faster than it argsorts the floats (5 ms at 410k
    splats on a 2-core AMD EPYC). With `keep` mostly set, the others are given the largest key and
    cut off after the sort, which is cheaper than gathering the kept ones first; mostly unset,
    gathering is cheaper (measured at 30 % and 80 % kept, 500k splats).
    """
    key = depth_keys(depths)
    if keep is None:
        return torch.sort(key, stable=True).indices
    n_keep = int(keep.sum())
    if 2 * n_keep >= key.numel():
        # The largest key is a NaN pattern `depth_keys` never produces: dropped ones sort last.
        key.masked_fill_(~keep, 0x7FFFFFFF)
        return torch.sort(key, stable=True).indices[:n_keep]
    kept = keep.nonzero().squeeze(1)
    return kept[torch.sort(key[kept], stable=True).indices]


def empty_bins(n: int, width: int, height: int, extents: Tensor | None = None) -> TileBins:
    ts = cst.TILE_SIZE
    tiles_x, tiles_y = math.ceil(width / ts), math.ceil(height / ts)
    z = torch.zeros(tiles_x * tiles_y, dtype=torch.int32)
    return TileBins(
        tiles_x, tiles_y, z, z.clone(), torch.zeros(0, dtype=torch.int32),
        torch.zeros(n + 1, dtype=torch.int32), torch.zeros(0, dtype=torch.int32),
        torch.full((n, 2), -1.0) if extents is None else extents,
    )  # fmt: skip


def bin_tiles(
    means2d: Tensor,
    conics: Tensor,
    opacities: Tensor,
    depths: Tensor,
    radii: Tensor,
    width: int,
    height: int,
    max_pairs: int = cst.MAX_PAIRS_DEFAULT,
    device: Runtime | str | None = None,
) -> TileBins:
    """Bin projected splats to tiles (not differentiable; the ids only select work).

    Args:
        means2d [N, 2], conics [N, 3], opacities [N], depths [N] (sort key), radii [N] (0 = culled),
        as `project` returns them. max_pairs: cap on (tile, splat) pairs, checked before any
        pair-sized allocation (`PairOverflowError`).
    Returns:
        `TileBins`. A splat goes to the tiles of its opacity-aware box (alpha >= 1/255 reachable)
        capped by its 3-sigma radius, which never changes an image, only saves work. Splats are
        depth-sorted once (stable), then per-chunk tile histograms, a scan and a scatter give
        every tile its list in depth order, deterministically, without sorting pairs.
    """
    rt = resolve_device(device)
    width, height = int(width), int(height)
    n = means2d.shape[0]
    bins = empty_bins(n, width, height, rt.empty(n, 2))
    if n == 0:
        return bins
    n_tiles = bins.n_tiles
    area = rt.empty(n, dtype=torch.int32)
    a_rects, a_ext, a_area = (
        rt.scratch(n, 4, dtype=torch.int32),
        rt.array(bins.extents, "out"),
        rt.array(area, "out"),
    )
    rt.run(
        "bin.cl", "bin_rects", (groups(n),), (64,),
        [i32(n), rt.input(means2d), rt.input(conics), rt.input(opacities), rt.input(radii, torch.int32),
         i32(bins.tiles_x), i32(bins.tiles_y), a_rects, a_ext, a_area],
    )  # fmt: skip
    bins.keep(rt, "extents", a_ext)
    area = area.to(torch.int64)
    n_pairs = int(area.sum())
    if n_pairs > max_pairs:
        raise PairOverflowError(n_pairs, max_pairs)
    bins.n_pairs = n_pairs
    if n_pairs == 0:
        return bins
    bins.pair_start[1:] = torch.cumsum(area, 0)
    # One stable depth sort of the splats that reach a tile; every tile list inherits it.
    order = stable_depth_order(depths.detach(), keep=area > 0).to(torch.int32)
    n_vis = bins.n_visible = int(order.numel())
    # Enough chunks to keep every compute unit busy with some balance, few enough that the
    # [chunks, tiles] histogram stays small.
    n_chunks = int(min(n_vis, max(1, min(1024, (1 << 22) // n_tiles, n_vis // 256 + 1))))
    chunk = (n_vis + n_chunks - 1) // n_chunks
    n_chunks = (n_vis + chunk - 1) // chunk
    # From here on nothing crosses but the order in and the lists out, read once at the end.
    a_order = rt.array(order)
    a_sorted = rt.scratch(n_vis, 4, dtype=torch.int32)
    rt.run("bin.cl", "bin_gather", (groups(n_vis),), (64,), [i32(n_vis), a_rects, a_order, a_sorted],
           wait=False)  # fmt: skip
    a_hist = rt.zeros(n_chunks, n_tiles, dtype=torch.int32)
    rt.run(
        "bin.cl", "bin_count", (n_chunks,), None,
        [i32(n_vis), i32(chunk), i32(n_tiles), i32(bins.tiles_x), a_sorted, a_hist], wait=False,
    )  # fmt: skip
    bins.tile_start = rt.empty(n_tiles, dtype=torch.int32)
    bins.tile_end = rt.empty(n_tiles, dtype=torch.int32)
    a_start, a_end = rt.array(bins.tile_start, "out"), rt.array(bins.tile_end, "out")
    rt.run(
        "bin.cl", "bin_scan_tiles", (groups(n_tiles),), (64,),
        [i32(n_tiles), i32(n_chunks), a_hist, a_end], wait=False,
    )  # fmt: skip
    rt.run("bin.cl", "bin_tile_ranges", (1,), None, [i32(n_tiles), a_start, a_end], wait=False)
    bins.ids = rt.empty(n_pairs, dtype=torch.int32)
    bins.pair_slot = rt.empty(n_pairs, dtype=torch.int32)
    a_ids, a_slot = rt.array(bins.ids, "out"), rt.array(bins.pair_slot, "out")
    rt.run(
        "bin.cl", "bin_scatter", (n_chunks,), None,
        [i32(n_vis), i32(chunk), i32(n_tiles), i32(bins.tiles_x), a_sorted, a_order, a_hist, a_start,
         *bins.arrays(rt, "pair_start"), a_ids, a_slot], wait=False,
    )  # fmt: skip
    rt.finish(a_start, a_end, a_ids, a_slot)
    for name, arr in (("tile_start", a_start), ("tile_end", a_end), ("ids", a_ids), ("pair_slot", a_slot)):
        bins.keep(rt, name, arr)
    return bins
