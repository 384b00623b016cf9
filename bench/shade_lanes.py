"""Benchmark: the packed shading pair as ``shade_lanes.cl`` (eight fragments per work-item in vector lanes) beside
``shade.cl`` (one per work-item), on the training's packed rows, in the same run.

Usage::

    python bench/shade_lanes.py [--sizes 160000 1000000] [--repeats 7] [--real float32] [--out bench/results/NAME.txt]

Rows: fragments x light mix (the soup's point + ambient, a directional light, three points, the mesh stage's point + SH
environment of degree 2 + bounce) x cached shadows (a transmittance column per point / directional light, as the soup
trains from iteration 600). The packed rows are laid out as ``render`` packs them (position, alpha, normal, the six
Cook-Torrance channels, then the visibility), a quarter of the cotangent rows zero (behind the compositing cut-off,
as a late soup's). Times: the best of ``--repeats`` calls (forward; backward including the host sum of the
light-gradient partials), the two kernels alternated call by call (the machine is shared); ratio = shade.cl /
lanes. 160k fragments is a late spot step at 200².
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np
import pyopencl.array as cla

from triplet_cl.device import get_device
from triplet_cl.lights import AmbientLight, BounceLight, DirectionalLight, PointLight, SHEnvironmentLight, pack_lights
from triplet_cl.ops import shade as shade_op

MIXES = {
    "pt+amb": lambda: [PointLight([1.0, 2.0, 2.0], [3.0] * 3), AmbientLight([0.1] * 3)],  # the soup's default
    "dir+amb": lambda: [DirectionalLight([0.3, 0.2, 1.0], [1.0] * 3), AmbientLight([0.1] * 3)],
    "3pt+amb": lambda: [PointLight([1.0, 2.0, 2.0], [3.0] * 3), PointLight([-2.0, 1.0, 1.0], [2.0] * 3),
                        PointLight([0.0, -2.0, 2.0], [1.0] * 3), AmbientLight([0.1] * 3)],
    # the mesh stage's: a point light, its SH environment of degree 2 and the traced bounce (a per-fragment radiance)
    "pt+env2+bnc": lambda: [PointLight([1.0, 2.0, 2.0], [3.0] * 3),
                            SHEnvironmentLight(np.r_[2.0, 0.3 * np.ones(8)][None].repeat(3, 0)), BounceLight()],
}


def case(dev, rng, P, lights, vis, real):
    table = pack_lights(lights)
    nv = table.num_shadowed if vis else 0
    nrm = rng.standard_normal((P, 3))
    nrm[:, 2] += 1.0
    named = [("POS", rng.uniform(-1, 1, (P, 3))), ("ALPHA", rng.uniform(0, 1, (P, 1))), ("NRM", nrm),
             ("MAT", rng.uniform(0.05, 0.95, (P, 6)))] + ([("VIS", rng.uniform(0, 1, (P, nv)))] if nv else [])
    if table.has_vertex_sh:  # the bounce's radiance (and an unused direction)
        named.append(("VL", rng.uniform(0, 0.5, (P, 6))))
    offs = np.cumsum([0] + [a.shape[1] for _, a in named])
    blocks = {n: (int(offs[i]), a.shape[1]) for i, (n, a) in enumerate(named)}
    fa = np.concatenate([a for _, a in named], 1).astype(real)
    _, inp = shade_op.prepare(np.zeros((1, 3)), np.ones((1, 3)), np.full((1, 6), 0.5), np.zeros(1, np.int32),
                              [0.0, 0.0, 4.0], lights, device=dev, real=real,
                              vlight=np.ones((1, 6)) if table.has_vertex_sh else None)  # (only its light table used)
    q = dev.queue
    pinp = shade_op.packed_inputs(dev, cla.to_device(q, fa), blocks, [0.0, 0.0, 4.0], table, inp.lt_i, inp.lt_f,
                                  "cook_torrance", True, real)
    v_rgb = rng.standard_normal((P, 3)).astype(real)
    v_rgb[rng.uniform(size=P) < 0.25] = 0.0
    return pinp, cla.to_device(q, v_rgb), cla.to_device(q, rng.standard_normal(P).astype(real))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", type=int, nargs="+", default=[160_000, 1_000_000])
    ap.add_argument("--repeats", type=int, default=7)
    ap.add_argument("--real", choices=["float32", "float64"], default="float32")
    ap.add_argument("--device", default=None)
    ap.add_argument("--out", default=None, help="also write the table here (a temporary file, then renamed)")
    args = ap.parse_args()
    dev = get_device(args.device)
    real = np.dtype(args.real).type
    rng = np.random.default_rng(0)
    lines = [f"# bench/shade_lanes.py  {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}  device: {dev.name}  "
             f"real={args.real} repeats={args.repeats}",
             f"{'fragments':>10} {'lights':>8} {'vis':>4} {'fwd shade.cl':>13} {'fwd lanes':>10} {'ratio':>6} "
             f"{'bwd shade.cl':>13} {'bwd lanes':>10} {'ratio':>6}"]
    print("\n".join(lines), flush=True)
    for P in args.sizes:
        for mix, make in MIXES.items():
            for vis in (False, True):
                pinp, v_rgb, v_a = case(dev, rng, P, make(), vis, real)
                best = {}
                for r in range(args.repeats + 1):  # round 0 builds the programs: not counted
                    for lanes in (False, True):
                        t0 = time.perf_counter()
                        shade_op.forward_packed(dev, pinp, lanes=lanes)
                        dev.queue.finish()
                        t1 = time.perf_counter()
                        shade_op.backward_packed(dev, pinp, v_rgb, v_a, lanes=lanes)
                        dev.queue.finish()
                        t2 = time.perf_counter()
                        if r:
                            for key, t in ((("f", lanes), t1 - t0), (("b", lanes), t2 - t1)):
                                best[key] = min(best.get(key, np.inf), t)
                f0, f1, b0, b1 = (best[("f", False)], best[("f", True)], best[("b", False)], best[("b", True)])
                line = (f"{P:>10} {mix:>8} {'yes' if vis else 'no':>4} {f0 * 1e3:>13.2f} {f1 * 1e3:>10.2f} "
                        f"{f0 / f1:>6.2f} {b0 * 1e3:>13.2f} {b1 * 1e3:>10.2f} {b0 / b1:>6.2f}")
                lines.append(line)
                print(line, flush=True)
    if args.out:
        out = Path(args.out)
        tmp = out.with_suffix(out.suffix + ".tmp")
        tmp.write_text("\n".join(lines) + "\n")
        tmp.replace(out)


if __name__ == "__main__":
    sys.exit(main())
