"""Benchmark: photometric loss (0.8·L1 + 0.2·D-SSIM) forward + backward, numpy/scipy vs OpenCL.

Usage: ``python bench/losses.py [--size 800] [--repeat 5] [--device SPEC]``. Prints one row per
backend: forward, backward and total median milliseconds on float32 ``[S, S, 3]`` images. The
OpenCL row works on device arrays (the renderer's output stays on the device); the last
row ("host in, opencl") is ``backend="opencl"`` on host images: upload both, run the kernels,
download the adjoint.
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import pyopencl.array as cla
from triplet_cl.autodiff import Context

from triplet_cl import get_device
from triplet_cl.losses import PhotometricLoss


def _time(fn, repeat):
    fn()  # warm-up (kernel build, caches)
    ts = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return 1e3 * float(np.median(ts))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--size", type=int, default=800)
    ap.add_argument("--repeat", type=int, default=5)
    ap.add_argument("--device", default=None)
    args = ap.parse_args()
    dev = get_device(args.device)
    rng = np.random.default_rng(0)
    x = rng.random((args.size, args.size, 3), dtype=np.float32)
    y = rng.random((args.size, args.size, 3), dtype=np.float32)
    xd, yd = cla.to_device(dev.queue, x), cla.to_device(dev.queue, y)

    rows = []
    for label, a, b in (("numpy/scipy", x, y), ("opencl", xd, yd)):
        fn = PhotometricLoss(0.2)
        state = {}

        def fwd(fn=fn, a=a, b=b, state=state):
            state["ctx"] = Context((True, False))
            fn.forward(state["ctx"], a, b)
            dev.queue.finish()

        def bwd(fn=fn, state=state):
            fn.backward(state["ctx"], np.asarray(1.0))
            dev.queue.finish()

        t_f = _time(fwd, args.repeat)
        t_b = _time(bwd, args.repeat)  # backward reads the saved context only, so it can repeat
        rows.append((label, t_f, t_b))

    def copies():  # backend='opencl' on host images
        fn = PhotometricLoss(0.2, backend="opencl")
        ctx = Context((True, False))
        fn.forward(ctx, x, y)
        v = fn.backward(ctx, np.asarray(1.0))[0]
        assert isinstance(v, np.ndarray)

    rows.append(("host in, opencl", float("nan"), float("nan"), _time(copies, args.repeat)))

    print(f"photometric loss fwd+bwd, float32 [{args.size}, {args.size}, 3], device: {dev.name}")
    print(f"{'backend':18} {'forward ms':>11} {'backward ms':>12} {'total ms':>9}")
    for r in rows:
        total = r[3] if len(r) == 4 else r[1] + r[2]
        print(f"{r[0]:18} {r[1]:11.1f} {r[2]:12.1f} {total:9.1f}")


if __name__ == "__main__":
    main()
