"""Benchmark: which OpenCL builtins the device runs as scalar library calls, and the kernels rewritten around them
(``kernels_cl/common/fast_math.h``) against an older commit's, in the same run.

Usage::

    python bench/fast_math.py [--baseline COMMIT] [--reps 30] [--out bench/results/NAME.txt]

Table 1: one kernel per builtin, ``y[i] = f(x[i])`` over 131 072 floats in (0, 1.5] (a kernel PoCL's work-group
loop vectorises), the minimum over ``--reps`` launches. Table 2: ``srgb_composite_fwd`` (``color.cl``, 200 × 200
pixels, KEEP_ROOT and SRGB_CLIP as training builds it) and ``vertex_attr_fwd`` (``vertex_attr.cl``, a 20 000-face
soup: 60 000 vertices, Cook-Torrance's six channels, face normals) built from the baseline's source
(``git show COMMIT:kernels_cl/...``, with this tree's headers, which the old sources also compile against) and from
this tree's, launched as each tree's op launches them (global size: one work-item per pixel, per channel value, per
vertex or per eight vertices), alternating; the minimum and median of each, the ratio of the minima, and the
largest difference of their outputs. Default baseline: ``HEAD``.
"""

from __future__ import annotations

import argparse
import subprocess
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
BUILTINS = ["exp(u)", "exp2(u)", "log(u)", "log2(u)", "log1p(u)", "sqrt(u)", "rsqrt(u)", "pow(u, 0.3f)", "sin(u)",
            "acos(u * 0.5f)", "atan2(u, 0.3f)", "cbrt(u)", "tl_log2(u)", "exp(tl_log2(u) * 0.28881133f)"]


def timed(q, fn, reps: int) -> tuple[float, float]:
    fn()
    q.finish()
    ts = []
    for _ in range(reps):
        t = time.perf_counter()
        fn()
        q.finish()
        ts.append(time.perf_counter() - t)
    return 1e3 * min(ts), 1e3 * float(np.median(ts))


def builtin_table(dev, reps: int) -> list[str]:
    import pyopencl as cl
    import pyopencl.array as cla

    src = '#include "real.h"\n#include "fast_math.h"\n' + "\n".join(
        f"__kernel void k{i}(__global const float* x, __global float* y) {{ const int i = get_global_id(0); "
        f"const float u = x[i]; y[i] = {f}; }}" for i, f in enumerate(BUILTINS))
    prg = dev.build_source(src, dev.build_options(None, np.float32), "bench_fast_math")
    n = 1 << 17
    x = cla.to_device(dev.queue, (np.random.default_rng(0).random(n) * 1.5 + 1e-3).astype(np.float32))
    y = cla.empty(dev.queue, n, np.float32)
    rows = [f"{'y[i] = f(x[i]), 131072 floats':40s} {'min ms':>8s} {'ns/value':>9s}"]
    for i, f in enumerate(BUILTINS):
        k = cl.Kernel(prg, f"k{i}")
        lo, _ = timed(dev.queue, lambda k=k: k(dev.queue, (n,), (64,), x.data, y.data), reps)
        rows.append(f"{f:40s} {lo:8.3f} {1e6 * lo / n:9.2f}")
    return rows


def kernel_table(dev, baseline: str, reps: int) -> list[str]:
    import pyopencl as cl
    import pyopencl.array as cla

    rng = np.random.default_rng(0)
    q = dev.queue
    npix, nv = 200 * 200, 60000
    C = cla.to_device(q, rng.random((npix, 3)).astype(np.float32))
    A = cla.to_device(q, (rng.random(npix) * 0.9 + 0.1).astype(np.float32))
    V = cla.to_device(q, rng.normal(size=(nv, 3)).astype(np.float32))
    nrm = cla.to_device(q, rng.normal(size=(nv // 3, 3)).astype(np.float32))
    mat = cla.to_device(q, rng.normal(size=(nv, 6)).astype(np.float32))
    alpha = cla.to_device(q, rng.normal(size=nv).astype(np.float32))

    def grid(n: int) -> tuple[tuple[int], tuple[int]]:
        return (-(-n // 64) * 64,), (64,)

    def srgb(src: str, per_value: bool):
        prg = dev.build_source(src, dev.build_options({"KEEP_ROOT": True, "SRGB_CLIP": True}, np.float32), "color")
        k = cl.Kernel(prg, "srgb_composite_fwd")
        root, out = cla.empty(q, (npix, 3), np.float32), cla.empty(q, (npix, 3), np.float32)
        g, loc = grid(3 * npix if per_value else npix)
        args = (C.data, A.data, np.float32(1), np.float32(1), np.float32(1), np.float32(1e-6), np.int32(npix),
                root.data, out.data)
        return (lambda: k(q, g, loc, *args)), out

    def vattr(src: str, lanes: int):
        defines = {"NMAT": 6, "SOFTPLUS_MASK": 0, "FACE_NRM": True, "NCONST": 0}
        prg = dev.build_source(src, dev.build_options(defines, np.float32), "vertex_attr")
        k = cl.Kernel(prg, "vertex_attr_fwd")
        out = cla.empty(q, (nv, 13), np.float32)
        g, loc = grid(-(-nv // lanes))
        return (lambda: k(q, g, loc, V.data, nrm.data, mat.data, alpha.data, np.int32(nv), out.data)), out

    def source(tree: str, name: str) -> str:
        if tree == "new":
            return (ROOT / "kernels_cl" / name).read_text()
        return subprocess.run(["git", "show", f"{baseline}:kernels_cl/{name}"], cwd=ROOT, check=True,
                              capture_output=True, text=True).stdout

    def shape(tree: str, name: str) -> tuple:
        """How this tree's op launches the kernel (read from its source: the new layouts say so in a comment)."""
        s = source(tree, name)
        if name == "color.cl":
            return ("per_value", "3 * npix" in s)
        return ("lanes", 8 if "VA_LANES" in s else 1)

    rows = [f"{'kernel':34s} {'tree':5s} {'min ms':>8s} {'median':>8s}"]
    for name, make in (("color.cl", srgb), ("vertex_attr.cl", vattr)):
        res = {}
        for _ in range(2):
            for tree in ("old", "new"):
                fn, out = make(source(tree, name), shape(tree, name)[1])
                lo, med = timed(q, fn, reps)
                prev = res.get(tree)
                res[tree] = (min(lo, prev[0]) if prev else lo, med if prev is None else min(med, prev[1]), out.get())
        label = "srgb_composite_fwd 200x200" if name == "color.cl" else "vertex_attr_fwd 60k vertices"
        for tree in ("old", "new"):
            rows.append(f"{label:34s} {tree:5s} {res[tree][0]:8.3f} {res[tree][1]:8.3f}")
        diff = float(np.abs(res["old"][2] - res["new"][2]).max())
        rows.append(f"{label:34s} o/n   {res['old'][0] / res['new'][0]:8.2f}   (largest output difference {diff:.2e})")
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--baseline", default="HEAD", help="the commit whose kernels are compared (default HEAD)")
    ap.add_argument("--reps", type=int, default=30, help="launches per measurement")
    ap.add_argument("--out", default=None, help="also write the tables here")
    args = ap.parse_args()
    from triplet_cl.device import get_device

    dev = get_device()
    sha = subprocess.run(["git", "rev-parse", "--short", args.baseline], cwd=ROOT, check=True, capture_output=True,
                         text=True).stdout.strip()
    lines = [f"# bench/fast_math.py on {dev.name}, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
             *builtin_table(dev, args.reps), "", f"# kernels: baseline {sha} (old) against this tree (new)",
             *kernel_table(dev, args.baseline, args.reps)]
    text = "\n".join(lines)
    print(text)
    if args.out:
        out = Path(args.out)
        tmp = out.with_suffix(out.suffix + ".tmp")
        tmp.write_text(text + "\n")
        tmp.replace(out)


if __name__ == "__main__":
    main()
