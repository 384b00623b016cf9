"""Exclusive prefix sums of int32 counts as offsets arrays (``kernels_cl/scan.cl`` on CPUs).

Used by the tile binning (tile and face offsets), the packed fragment layout (per-pixel offsets)
and the ray tracer's packing.
"""

from __future__ import annotations

import numpy as np
import pyopencl as cl
import pyopencl.array as cla
from pyopencl.scan import InclusiveScanKernel

from ..device import Device
from .common import device_empty

SCAN_BLOCK = 4096  # counts per work-item of the CPU scan (kernels_cl/scan.cl) ...
SCAN_SERIAL = 1 << 18  # ... up to this many counts, one work-item


def _scan_kernel(device: Device) -> InclusiveScanKernel:
    return device.cached(("scan", "int32-sum"), lambda: InclusiveScanKernel(device.ctx, np.int32, "a+b", neutral="0"))


def prefix_offsets(device: Device, counts: cla.Array, total: bool = True) -> tuple[cla.Array, int | None]:
    """Exclusive prefix sum of ``counts [n]`` (int32) as an ``[n+1]`` offsets array, and the total
    (one small blocking read back; ``total=False`` skips it and returns None). CPU devices:
    ``kernels_cl/scan.cl``; others: pyopencl's scan."""
    n = counts.shape[0]
    q, alloc = device.queue, device.allocator
    if n == 0:
        return cla.zeros(q, 1, np.int32, allocator=alloc), 0 if total else None
    if device.is_cpu:
        off = device_empty(q, n + 1, np.int32, allocator=alloc)
        block = n if n <= SCAN_SERIAL else SCAN_BLOCK
        nb = -(-n // block)
        sums = device_empty(q, nb, np.int32, allocator=alloc) if nb > 1 else off  # one block reads no sum
        args = (np.int32(n), np.int32(block), np.int32(nb))
        if nb > 1:
            device.kernel("scan", "scan_block_sums")(q, (nb,), (1,), counts.data, *args, sums.data)
            device.kernel("scan", "scan_block_offsets")(q, (1,), (1,), sums.data, np.int32(nb))
        device.kernel("scan", "scan_block_write")(q, (nb,), (1,), counts.data, *args, sums.data, off.data)
    else:
        off = cla.zeros(q, n + 1, np.int32, allocator=alloc)
        incl = device_empty(q, n, np.int32, allocator=alloc)
        _scan_kernel(device)(counts, incl, queue=q)
        # off[1:] = incl  (a sliced array's .data would not carry the offset into the scan kernel)
        cl.enqueue_copy(q, off.data, incl.data, dst_offset=4, byte_count=4 * n)
    if not total:
        return off, None
    tail = np.empty(1, np.int32)
    cl.enqueue_copy(q, tail, off.data, src_offset=4 * n)
    return off, int(tail[0])


__all__ = ["SCAN_BLOCK", "SCAN_SERIAL", "prefix_offsets"]
