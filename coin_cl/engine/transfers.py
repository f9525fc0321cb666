"""Counted host <-> device copies of the discrete-memory path (docs/DESIGN.md section 3: "elsewhere an
explicit, counted transfer. The runtime can report how many bytes crossed per iteration").

On a host-unified-memory device the runtime aliases torch's memory and nothing is counted. On a
device without it (a discrete GPU), or with COIN_CL_DISCRETE=1 on any device, every input is
copied into a device-only buffer and every output copied back; each copy adds its bytes here and,
once the queue has drained, its device time (OpenCL event profiling: from the copy's start to its
end on the device, so host overheads and the wait for earlier kernels are not in it).
"""

from __future__ import annotations

from dataclasses import dataclass, field, fields


@dataclass
class TransferStats:
    """Running totals of the copies between torch (host) and OpenCL buffers."""

    bytes_in: int = 0  # host -> device
    bytes_out: int = 0  # device -> host
    copies: int = 0
    reused: int = 0  # bytes an op read from a buffer already on the device instead of copying in
    seconds: float = 0.0  # device time of the copies whose events have completed
    _pending: list = field(default_factory=list, repr=False)  # events not yet timed

    @property
    def bytes(self) -> int:
        return self.bytes_in + self.bytes_out

    def add(self, nbytes: int, event, inbound: bool) -> None:
        """Count one copy of `nbytes`; `event` (a profiled pyopencl event) is timed by `settle`."""
        if inbound:
            self.bytes_in += nbytes
        else:
            self.bytes_out += nbytes
        self.copies += 1
        self._pending.append(event)

    def settle(self) -> None:
        """Add the device time of the pending copies; call once the queue has finished."""
        for ev in self._pending:
            try:
                self.seconds += (ev.profile.end - ev.profile.start) * 1e-9
            except Exception:  # a queue without profiling: bytes stay counted, time is not
                pass
        self._pending.clear()

    def snapshot(self) -> dict[str, float]:
        """The totals as a plain dict (bytes_in, bytes_out, bytes, copies, seconds)."""
        out = {f.name: getattr(self, f.name) for f in fields(self) if not f.name.startswith("_")}
        out["bytes"] = self.bytes
        return out

    @staticmethod
    def delta(after: dict[str, float], before: dict[str, float]) -> dict[str, float]:
        """What crossed between two snapshots (a benchmark step, a training iteration)."""
        return {k: after[k] - before[k] for k in after}
