"""The engine's exceptions (imported by the fast path and the twins alike)."""

from __future__ import annotations


class NoDeviceError(RuntimeError):
    """No OpenCL platform/device matches the request, or none can build kernels."""


class PairOverflowError(RuntimeError):
    """More (tile, Gaussian) pairs than the cap allows: raised before anything is allocated."""

    def __init__(self, n_pairs: int, max_pairs: int):
        super().__init__(
            f"{n_pairs} (tile, Gaussian) pairs exceed max_pairs={max_pairs}: splats this large "
            "cover the screen many times over; shrink huge scales, cull them, or raise max_pairs"
        )
        self.n_pairs, self.max_pairs = n_pairs, max_pairs


class DeviceLimitError(RuntimeError):
    """A device limit (work-group size, local memory, allocation size) is below what a kernel
    needs, and no smaller variant fits: the message names the device, the limit and what to do."""


class NonFiniteInputError(ValueError):
    """A renderer input that must be finite (the camera, the background colour) holds NaN or Inf:
    the message names the argument and its value. A ValueError: bad input, not a device fault."""
