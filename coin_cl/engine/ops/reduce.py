"""Fixed-order gradient reduction (kernels/reduce.cl) behind the deterministic rasterize backward."""

from __future__ import annotations

from torch import Tensor

from coin_cl.engine.ops._util import groups, i32
from coin_cl.engine.ops.bin import TileBins
from coin_cl.engine.runtime import DeviceArray, Runtime


def reduce_pair_grads(
    rt: Runtime,
    bins: TileBins,
    contrib: DeviceArray,
    outs: list[Tensor],
    channels: int,
) -> None:
    """Sum each splat's per-tile gradient shares in a fixed order (its tiles row by row).

    Args:
        bins: the `bin_tiles` result (its pair_start [N + 1] and pair_slot [P] int32, read from
        the device buffers binning left there); contrib: the device buffer of
        [P, 6 + C] shares the rasterize backward wrote; outs: v_means2d [N, 2], v_conics [N, 3],
        v_opacities [N], v_features [N, C] float32, every element written (zeros for splats in
        no tile). Bit-reproducible: no atomics, the same order on every run and device.
    """
    n = bins.pair_start.numel() - 1
    if n <= 0:
        return
    rt.run(
        "reduce.cl", "reduce_grads", (groups(n),), (64,),
        # kept on the device: the projection's backward reads them next
        [i32(n), *bins.arrays(rt, "pair_start", "pair_slot"), contrib,
         *[rt.array(t, "out", keep=True) for t in outs]],
        defines={"NUM_CHANNELS": channels},
    )  # fmt: skip
