"""Page-locked staging for the copies of the discrete-memory path.

A copy between an OpenCL buffer and pageable host memory (a torch tensor) makes the driver stage
it through its own page-locked memory, chunk by chunk: about 6.4 GB/s on an NVIDIA H200 through
its OpenCL. From page-locked memory the copy is one DMA transfer. So each copy of the discrete
path goes through a block of page-locked memory this pool owns (a buffer allocated with
CL_MEM_ALLOC_HOST_PTR and mapped once, the way NVIDIA's OpenCL guide obtains pinned memory):
host memory to the block with torch's parallel copy, then the block to the device, or the other
way round. Blocks are held from the copy's enqueue to the queue's finish, then reused; sizes are
powers of two from 64 KiB, and the pool keeps at most `max_bytes` (larger demands copy directly).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np
import torch

MIN_BLOCK = 1 << 16  # bytes: small copies are cheap either way; fewer block sizes to keep
MAX_POOL_BYTES = 1 << 30  # page-locked memory the pool may hold in all


@dataclass
class PinnedBlock:
    """One page-locked block: the OpenCL buffer that owns it and its mapped host view."""

    nbytes: int
    buf: object
    host: np.ndarray  # uint8 [nbytes], the mapped memory

    def view(self, nbytes: int) -> np.ndarray:
        return self.host[:nbytes]


@dataclass
class PinnedPool:
    """Page-locked blocks by size, for one OpenCL context and queue."""

    context: object
    queue: object
    max_bytes: int = MAX_POOL_BYTES
    held: int = 0  # bytes of all blocks made (in use or free)
    _free: dict = field(default_factory=dict)  # nbytes -> [PinnedBlock]

    def take(self, nbytes: int) -> PinnedBlock | None:
        """A block of at least `nbytes`; None when the pool would grow past `max_bytes`."""
        size = max(MIN_BLOCK, 1 << (max(int(nbytes), 1) - 1).bit_length())
        free = self._free.get(size)
        if free:
            return free.pop()
        if self.held + size > self.max_bytes:
            return None
        import pyopencl as cl

        buf = cl.Buffer(self.context, cl.mem_flags.READ_WRITE | cl.mem_flags.ALLOC_HOST_PTR, size)
        flags = cl.map_flags.READ | cl.map_flags.WRITE
        host, _ = cl.enqueue_map_buffer(self.queue, buf, flags, 0, (size,), np.uint8, is_blocking=True)
        self.held += size
        return PinnedBlock(size, buf, host)

    def give(self, block: PinnedBlock) -> None:
        """Return a block once the queue has finished every copy that used it."""
        self._free.setdefault(block.nbytes, []).append(block)


def fill(block: PinnedBlock, src: torch.Tensor) -> np.ndarray:
    """Copy a contiguous CPU tensor's bytes into the block; the block's view of them."""
    nbytes = src.numel() * src.element_size()
    dst = block.view(nbytes)
    torch.from_numpy(dst).copy_(_bytes(src))
    return dst


def drain(block: PinnedBlock, dst: torch.Tensor) -> None:
    """Copy the block's first bytes into a contiguous CPU tensor."""
    nbytes = dst.numel() * dst.element_size()
    _bytes(dst).copy_(torch.from_numpy(block.view(nbytes)))


def _bytes(t: torch.Tensor) -> torch.Tensor:
    """The tensor's memory as a flat uint8 tensor (a view: writing it writes the tensor)."""
    # Through numpy: a contiguous tensor may still carry stride 0 on a size-1 axis, which torch's
    # dtype view refuses and numpy's flat view ignores.
    return torch.from_numpy(t.detach().numpy().reshape(-1).view(np.uint8))
