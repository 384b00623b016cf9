"""The mesh stage's Gaussian pixel filter on its own (issue 20): a supersampled render's radiance and alpha filtered
down to the photos' pixels and the adjoint back up (``ops.downsample.gauss_down_rgba`` / ``gauss_up_rgba``, the
path ``render.PixelFilterRGBA`` takes every mesh step), beside the per-array filters (``gauss_down`` / ``gauss_up`` of
the radiance and of the alpha: the same values, two launches per pass), in the same process.

    python bench/pixel_filter_step.py [--sizes 96,200,400] [--f 3] [--sigmas 0.49,1.0] [--reps 15]

Run it from two trees (``git worktree add --detach /tmp/old REV``; ``PYTHONPATH=/tmp/old python
bench/pixel_filter_step.py``) alternately to compare commits: PoCL's timings swing ±25 % with the machine's load.
Per row the minimum over ``--reps`` (load only adds time) and the median, in ms.
"""

from __future__ import annotations

import argparse
import time

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="96,200,400", help="comma-separated output sizes (square), photo pixels")
    ap.add_argument("--f", type=int, default=3, help="the supersampling factor (the mesh stage's default: 3)")
    ap.add_argument("--sigmas", default="0.49,1.0", help="filter standard deviations, photo pixels (the dev "
                    "captures read 0.46-0.49 from their photos)")
    ap.add_argument("--reps", type=int, default=15)
    args = ap.parse_args()

    import pyopencl.array as cla

    import triplet_cl
    from triplet_cl.device import get_device
    from triplet_cl.ops.downsample import gauss_down, gauss_down_rgba, gauss_up, gauss_up_rgba

    dev = get_device()
    q = dev.queue
    rng = np.random.default_rng(0)
    f = args.f
    print(f"# bench/pixel_filter_step.py ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}), triplet_cl from "
          f"{triplet_cl.__file__}, f = {f}, {dev.info.device_name}")
    print("| output | sigma | rgba down | rgba up | rgba total (min / median) | per-array total | ratio |")
    print("|---|---|---|---|---|---|---|")
    for n in (int(s) for s in args.sizes.split(",")):
        x = cla.to_device(q, rng.random((n * f, n * f, 3), dtype=np.float32))
        a = cla.to_device(q, rng.random((n * f, n * f), dtype=np.float32))
        v = cla.to_device(q, rng.random((n, n, 3), dtype=np.float32))
        va = cla.to_device(q, rng.random((n, n), dtype=np.float32))
        for sigma in (float(s) for s in args.sigmas.split(",")):
            jobs = {"down": lambda x=x, a=a, s=sigma: gauss_down_rgba(dev, x, a, f, s),
                    "up": lambda v=v, va=va, s=sigma: gauss_up_rgba(dev, v, va, f, s),
                    "per": lambda x=x, a=a, v=v, va=va, s=sigma: (
                        gauss_down(dev, x, f, s), gauss_down(dev, a, f, s), gauss_up(dev, v, f, s),
                        gauss_up(dev, va, f, s))}
            for fn in jobs.values():  # builds
                fn()
                fn()
            q.finish()
            t = {k: [] for k in jobs}
            for _ in range(args.reps):
                for k, fn in jobs.items():
                    t0 = time.perf_counter()
                    fn()
                    q.finish()
                    t[k].append(1e3 * (time.perf_counter() - t0))
            tot = [d + u for d, u in zip(t["down"], t["up"], strict=True)]
            print(f"| {n}² | {sigma:g} | {min(t['down']):.2f} | {min(t['up']):.2f} | {min(tot):.2f} / "
                  f"{np.median(tot):.2f} | {min(t['per']):.2f} | {min(t['per']) / min(tot):.2f}× |", flush=True)


if __name__ == "__main__":
    main()
