"""Benchmark of the shading op: median forward / backward time per call.

    python bench/shade.py [--sizes 100000 1000000] [--repeats 5] [--device SPEC]

Table: fragments x BRDF x light mix. Times are for validated device-resident inputs (what the
training loop does), including the host sum of the light-gradient partials in the backward pass.
"""

from __future__ import annotations

import argparse
import statistics
import time

import numpy as np

from triplet_cl.device import get_device
from triplet_cl.lights import AmbientLight, DirectionalLight, PointLight, SHEnvironmentLight, VertexSHLight
from triplet_cl.materials import BRDFS
from triplet_cl.ops import shade as shade_op
from triplet_cl.ops.common import to_device

MIXES = {
    "dir+amb": lambda rng: [DirectionalLight([0.3, 0.2, 1.0], [1.0] * 3), AmbientLight([0.1] * 3)],
    "vsh+amb": lambda rng: [VertexSHLight(), AmbientLight([0.1] * 3)],
    # the soup's default mix: a point light and the ambient light
    "pt+amb": lambda rng: [PointLight([1.0, 2.0, 2.0], [3.0] * 3), AmbientLight([0.1] * 3)],
    # the mesh stage's mixes: a point light and its SH environment (degree 2: a dielectric's, 8: a metal's)
    "pt+env2": lambda rng: [PointLight([1.0, 2.0, 2.0], [3.0] * 3),
                            SHEnvironmentLight(rng.standard_normal((3, 9)) * 0.2 + np.r_[2.0, np.zeros(8)])],
    "pt+env8": lambda rng: [PointLight([1.0, 2.0, 2.0], [3.0] * 3),
                            SHEnvironmentLight(rng.standard_normal((3, 81)) * 0.2 + np.r_[2.0, np.zeros(80)])],
    "4pt+env3+vsh": lambda rng: [PointLight(rng.standard_normal(3) * 2, [3.0] * 3) for _ in range(4)]
    + [SHEnvironmentLight(rng.standard_normal((3, 16)) * 0.2 + np.r_[2.0, np.zeros(15)]), VertexSHLight()],
}


def _time(fn, repeats: int) -> float:
    fn()  # warm-up (and first-use compilation)
    ts = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t0)
    return statistics.median(ts)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[100_000, 1_000_000])
    ap.add_argument("--repeats", type=int, default=5)
    ap.add_argument("--device", default=None)
    ap.add_argument("--brdfs", nargs="+", default=list(BRDFS), choices=list(BRDFS))
    ap.add_argument("--mixes", nargs="+", default=list(MIXES), choices=list(MIXES))
    args = ap.parse_args()
    dev = get_device(args.device)
    rng = np.random.default_rng(0)
    print(f"device: {dev.name}")
    print(f"{'fragments':>10} {'brdf':>14} {'lights':>14} {'forward ms':>11} {'backward ms':>12} {'Mfrag/s fwd':>12}")
    for P in args.sizes:
        pos = rng.uniform(-1, 1, (P, 3)).astype(np.float32)
        nrm = rng.standard_normal((P, 3)).astype(np.float32)
        fid = np.where(rng.random(P) < 0.1, -1, 0).astype(np.int32)
        vlight = np.concatenate([rng.uniform(0, 1, (P, 3)), rng.standard_normal((P, 3))], 1).astype(np.float32)
        v_rgb = to_device(dev.queue, rng.standard_normal((P, 3)).astype(np.float32))
        for brdf in args.brdfs:
            mat = rng.uniform(0.05, 0.95, (P, shade_op.num_material_channels(brdf))).astype(np.float32)
            for mix in args.mixes:
                lights = MIXES[mix](rng)
                _, inp = shade_op.prepare(pos, nrm, mat, fid, [0.0, 0.0, 4.0], lights, brdf=brdf, vlight=vlight,
                                          device=dev)

                def fwd(inp=inp):
                    shade_op.forward(dev, inp)
                    dev.queue.finish()

                def bwd(inp=inp, v_rgb=v_rgb):
                    shade_op.backward(dev, inp, v_rgb)
                    dev.queue.finish()

                tf, tb = _time(fwd, args.repeats), _time(bwd, args.repeats)
                print(f"{P:>10} {brdf:>14} {mix:>14} {tf * 1e3:>11.1f} {tb * 1e3:>12.1f} {P / tf / 1e6:>12.1f}",
                      flush=True)


if __name__ == "__main__":
    main()
