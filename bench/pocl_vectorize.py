"""Benchmark: which kernel shapes the OpenCL CPU device vectorises across work-items (what to write kernels as).

Usage::

    python bench/pocl_vectorize.py [--n 1048576] [--repeats 5] [--out bench/results/NAME.txt]

The same small computations written in different shapes, 1M work-items each (work-groups of 64): normalising a
3-vector stored interleaved ([n, 3], as the packed fragment and vertex arrays are) or planar ([3, n]), with scalar
code or a ``float3``; a transcendental (``exp2(log2(x) · k)``, as the sRGB root; ``exp(log(x) · k)``); a reduction
loop of run-time length (3 channels); and a gather through ``i / 3``. Per row: the best time of ``--repeats``
launches and, on PoCL, whether the compiled work-group function uses AVX registers (``ymm``/``zmm``, read from PoCL's
kernel cache with ``objdump``: ``vector`` yes/no, ``?`` where that cannot be read). The rows are the measurements
behind ``kernels_cl/ssim_exact.cl``'s element-wise kernels of session 43 (since session 58 eight values per
work-item in explicit vector lanes, faster still): PoCL 3.1 vectorises a scalar kernel whose
consecutive work-items read consecutive values, and nothing that holds a ``float3`` or an interleaved load.
"""

from __future__ import annotations

import argparse
import glob
import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pyopencl as cl

from triplet_cl.device import get_device

KERNELS = {
    "interleaved [n,3], float3": """
        __kernel void k(__global const float* a, __global float* b, const int n, const int C) {
            const int p = get_global_id(0);
            const float3 v = vload3(p, a);
            vstore3(v * rsqrt(fmax(dot(v, v), 1e-12f)), p, b);
        }""",
    "interleaved [n,3], scalar": """
        __kernel void k(__global const float* a, __global float* b, const int n, const int C) {
            const int p = get_global_id(0);
            const float x = a[3 * p], y = a[3 * p + 1], z = a[3 * p + 2];
            const float r = rsqrt(fmax(x * x + y * y + z * z, 1e-12f));
            b[3 * p] = x * r; b[3 * p + 1] = y * r; b[3 * p + 2] = z * r;
        }""",
    "planar [3,n], float3": """
        __kernel void k(__global const float* a, __global float* b, const int n, const int C) {
            const int p = get_global_id(0);
            const float3 v = (float3)(a[p], a[n + p], a[2 * n + p]);
            const float3 o = v * rsqrt(fmax(v.x * v.x + v.y * v.y + v.z * v.z, 1e-12f));
            b[p] = o.x; b[n + p] = o.y; b[2 * n + p] = o.z;
        }""",
    "planar [3,n], scalar": """
        __kernel void k(__global const float* a, __global float* b, const int n, const int C) {
            const int p = get_global_id(0);
            const float x = a[p], y = a[n + p], z = a[2 * n + p];
            const float r = rsqrt(fmax(x * x + y * y + z * z, 1e-12f));
            b[p] = x * r; b[n + p] = y * r; b[2 * n + p] = z * r;
        }""",
    "planar, run-time channel loop": """
        __kernel void k(__global const float* a, __global float* b, const int n, const int C) {
            const int p = get_global_id(0);
            float s = 0.0f;
            for (int c = 0; c < C; ++c) s += a[c * n + p] * a[c * n + p];
            b[p] = s;
        }""",
    "gather a[i / 3]": """
        __kernel void k(__global const float* a, __global float* b, const int n, const int C) {
            const int p = get_global_id(0);
            b[p] = a[p] / fmax(a[p / 3 + n], 1e-4f);
        }""",
    "exp2(log2(x) * k)": """
        __kernel void k(__global const float* a, __global float* b, const int n, const int C) {
            const int p = get_global_id(0);
            b[p] = exp2(log2(a[p]) * 0.41666667f);
        }""",
    "exp(log(x) * k)": """
        __kernel void k(__global const float* a, __global float* b, const int n, const int C) {
            const int p = get_global_id(0);
            b[p] = exp(log(a[p]) * 0.41666667f);
        }""",
}


def vector_registers(before: set[str]) -> str:
    """``yes`` / ``no``: whether the newest PoCL cache entry of kernel ``k`` (not in ``before``) uses ymm/zmm
    registers; ``?`` when there is no PoCL cache or no objdump."""
    objdump = shutil.which("objdump")
    cache = os.path.expanduser("~/.cache/pocl/kcache")
    if objdump is None or not os.path.isdir(cache):
        return "?"
    new = [p for p in glob.glob(f"{cache}/*/*/k/*/k.so") if p not in before]
    if not new:
        return "?"
    dis = subprocess.run([objdump, "-d", max(new, key=os.path.getmtime)], capture_output=True, text=True).stdout
    return "yes" if ("ymm" in dis or "zmm" in dis) else "no"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--n", type=int, default=1 << 20, help="work-items per launch (a multiple of 64)")
    ap.add_argument("--repeats", type=int, default=5, help="timed launches per kernel (best kept)")
    ap.add_argument("--out", default=None, help="also write the table to this file")
    args = ap.parse_args()
    n = -(-args.n // 64) * 64
    dev = get_device()
    q = dev.queue
    rng = np.random.default_rng(0)
    a = cl.Buffer(dev.ctx, cl.mem_flags.READ_ONLY | cl.mem_flags.COPY_HOST_PTR,
                  hostbuf=rng.uniform(0.01, 1.0, 4 * n).astype(np.float32))
    b = cl.Buffer(dev.ctx, cl.mem_flags.WRITE_ONLY, 4 * 4 * n)
    lines = [f"# bench/pocl_vectorize.py  {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}  device: {dev.name}  "
             f"n={n}", f"{'kernel shape':<32}{'ms':>9}{'ns/item':>9}  vector"]
    for name, src in KERNELS.items():
        before = set(glob.glob(os.path.expanduser("~/.cache/pocl/kcache/*/*/k/*/k.so")))
        # a comment with the row's name makes each build a distinct cache entry
        prg = cl.Program(dev.ctx, f"/* {name} */\n" + src).build()
        k = prg.k
        ts = []
        for _ in range(args.repeats + 1):
            q.finish()
            t0 = time.perf_counter()
            k(q, (n,), (64,), a, b, np.int32(n), np.int32(3))  # C = 3 channels (the loop row)
            q.finish()
            ts.append(time.perf_counter() - t0)
        best = min(ts[1:])
        lines.append(f"{name:<32}{1e3 * best:>9.3f}{1e9 * best / n:>9.2f}  {vector_registers(before)}")
    text = "\n".join(lines)
    print(text)
    if args.out:
        Path(args.out).write_text(text + "\n")


if __name__ == "__main__":
    main()
