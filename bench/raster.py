"""Benchmark of the whole rasterization chain, forward and backward (issue: rasterization).

Chain: project → bin → raster (K nearest) → interpolate (RGB + alpha) → coverage → composite, and
the adjoint back to vertex positions, colours, alphas and sigma. Median of ``--runs`` runs after a
warm-up, on the default device (``TRIPLET_DEVICE`` selects another).

Scenes:
  surface  small triangles in a thin shell around a sphere covering about half the image
           (~7 fragments per covered pixel),
  dense    triangles filling a ball (~25–35 fragments per covered pixel).
Peer: with ``mitsuba`` importable (variant llvm_ad_rgb), the opaque job — K=1, per-vertex colour,
same mesh and camera, gradient w.r.t. vertex colours — by Mitsuba 3's ``direct`` integrator at 1 spp.

    python bench/raster.py                      # the table of the issue (long on 2 CPU cores)
    python bench/raster.py --quick              # 400², 100k faces, K=30 and the Mitsuba comparison
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time

import numpy as np

from triplet_cl import get_device
from triplet_cl.camera import Camera
from triplet_cl.ops.composite import composite, composite_backward, coverage
from triplet_cl.ops.interpolate import interpolate, interpolate_backward
from triplet_cl.ops.mesh import DeviceMesh
from triplet_cl.ops.raster import project, project_backward, raster_backward, rasterize


def fibonacci_sphere(n: int) -> np.ndarray:
    i = np.arange(n) + 0.5
    phi = np.arccos(1 - 2 * i / n)
    th = math.pi * (1 + 5**0.5) * i
    return np.stack([np.cos(th) * np.sin(phi), np.sin(th) * np.sin(phi), np.cos(phi)], 1)


def make_soup(kind: str, M: int, seed: int = 0):
    """A triangle soup of M faces: 'surface' (thin shell, radius 1) or 'dense' (filled ball)."""
    rng = np.random.default_rng(seed)
    if kind == "surface":
        c = fibonacci_sphere(M) * (1 + rng.normal(0, 0.01, (M, 1)))
        # triangle size chosen so that a covered pixel sees ~7 fragments (front and back of the shell)
        r = 1.65 * math.sqrt(4 * math.pi * 3.5 / M / 0.43) / 2
    else:
        c = rng.normal(0, 1, (M, 3))
        c *= (rng.uniform(0, 1, (M, 1)) ** (1 / 3)) / np.linalg.norm(c, axis=1, keepdims=True)
        # triangle size chosen so that a covered pixel sees ~25-35 fragments
        r = 3.0 * math.sqrt(30 * math.pi / M / 0.43 * 0.75) / 2
    d = rng.normal(0, 1, (M, 3, 3))
    d /= np.linalg.norm(d, axis=2, keepdims=True)
    V = (c[:, None, :] + r * d).reshape(-1, 3).astype(np.float32)
    F = np.arange(3 * M, dtype=np.int32).reshape(M, 3)
    return V, F


def camera(res: int) -> Camera:
    # sphere of radius 1 at distance 3.2 with a 40° field of view covers ~half the image
    return Camera.look_at([0.0, 0.0, 3.2], [0, 0, 0], [0, 1, 0], 40.0, res, res)


class Chain:
    def __init__(self, dev, V, F, cam, K, sigma=1.0):
        self.dev, self.V, self.cam, self.K, self.sigma = dev, V, cam, K, sigma
        self.mesh = DeviceMesh(dev, F, len(V))
        rng = np.random.default_rng(1)
        self.col = rng.uniform(0, 1, (len(V), 3)).astype(np.float32)
        self.alv = np.full((len(V), 1), 0.5, np.float32)
        import pyopencl.array as cla

        q = dev.queue
        self.Vd = cla.to_device(q, V)
        self.cold = cla.to_device(q, self.col)
        self.ald = cla.to_device(q, self.alv)
        self.v_img = cla.to_device(q, rng.standard_normal((cam.height, cam.width, 3)).astype(np.float32))

    def forward(self):
        d = self.dev
        self.vs = project(d, self.Vd, self.cam)
        self.fr = rasterize(d, self.vs, self.mesh, self.cam.width, self.cam.height, self.K)
        self.feat = interpolate(d, self.cold, self.fr)
        self.a = interpolate(d, self.ald, self.fr).reshape(self.fr.shape)
        self.win = coverage(d, self.fr, self.sigma)
        self.img, self.trans, self.ncon = composite(d, self.fr, self.feat, self.a, np.ones(3), win=self.win)
        d.queue.finish()

    def backward(self):
        d, fr = self.dev, self.fr
        vf, va, vw, _ = composite_backward(d, fr, self.feat, self.a, np.ones(3), self.ncon, self.trans, self.v_img,
                                           win=self.win)
        _, vb = interpolate_backward(d, self.cold, fr, vf)
        _, vb = interpolate_backward(d, self.ald, fr, va.reshape(*fr.shape, 1), v_bary_acc=vb)
        v_vs, _ = raster_backward(d, fr, v_bary=vb, v_win=vw, sigma=self.sigma)
        project_backward(d, self.Vd, self.cam, v_vs)
        d.queue.finish()


def timed(fn, runs):
    fn()  # warm-up (kernel compilation, PoCL work-group specialisation)
    ts = []
    for _ in range(runs):
        t = time.perf_counter()
        fn()
        ts.append(time.perf_counter() - t)
    return statistics.median(ts) * 1e3


def frag_stats(ch: Chain):
    cnt = ch.fr.count.get()
    cov = cnt > 0
    return float(cnt[cov].mean()) if cov.any() else 0.0, float(cov.mean())


def mitsuba_opaque(V, F, col, cam: Camera, runs: int):
    """Mitsuba 3 llvm_ad_rgb: per-vertex colour, direct integrator 1 spp, d(image·v)/d(colour)."""
    try:
        import drjit as dr
        import mitsuba as mi

        mi.set_variant("llvm_ad_rgb")
    except Exception as exc:  # noqa: BLE001
        return None, f"mitsuba unavailable ({type(exc).__name__}: {exc})"
    fov = math.degrees(2 * math.atan(cam.width / 2 / cam.fx))
    c2w = cam.c2w.copy()
    c2w[:3, 0] *= -1  # Mitsuba camera: +X left, +Y up, +Z forward
    c2w[:3, 1] *= -1
    mesh = mi.Mesh("soup", len(V), len(F), has_vertex_normals=False, has_vertex_texcoords=False)
    params = mi.traverse(mesh)
    params["vertex_positions"] = dr.ravel(mi.Point3f(V[:, 0], V[:, 1], V[:, 2]))
    params["faces"] = dr.ravel(mi.Vector3u(F[:, 0], F[:, 1], F[:, 2]))
    mesh.add_attribute("vertex_color", 3, dr.ravel(mi.Color3f(col[:, 0], col[:, 1], col[:, 2])))
    params.update()
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct"},
        "sensor": {"type": "perspective", "fov": fov, "fov_axis": "x", "to_world": mi.ScalarTransform4f(c2w),
                   "film": {"type": "hdrfilm", "width": cam.width, "height": cam.height, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 1}},
        "emitter": {"type": "constant"},
        "soup": {"type": "ply", "filename": _write_ply(V, F, col), "bsdf": {
            "type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}}},
    })
    sp = mi.traverse(scene)
    key = "soup.vertex_color"
    dr.enable_grad(sp[key])
    sp.update()

    def step():
        img = mi.render(scene, sp, spp=1, seed=0)
        dr.backward(dr.sum(img))
        g = dr.grad(sp[key])
        dr.eval(g)
        dr.sync_thread()

    return timed(step, runs), "llvm_ad_rgb, direct, 1 spp"


def _write_ply(V, F, col):
    import tempfile

    import trimesh

    path = tempfile.NamedTemporaryFile(suffix=".ply", delete=False).name
    m = trimesh.Trimesh(V, F, vertex_colors=(np.clip(col, 0, 1) * 255).astype(np.uint8), process=False)
    m.export(path)
    return path


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="only 400², 100k faces, K=30 and the peer")
    ap.add_argument("--res", type=int, nargs="*", default=[200, 400, 800])
    ap.add_argument("--faces", type=int, nargs="*", default=[10_000, 100_000, 1_000_000])
    ap.add_argument("--K", type=int, nargs="*", default=[1, 30, 150])
    ap.add_argument("--scenes", nargs="*", default=["surface", "dense"])
    ap.add_argument("--no-peer", action="store_true")
    args = ap.parse_args(argv)
    dev = get_device()
    print(f"device: {dev.name}  ({dev.info.type}, {dev.info.compute_units} CUs)")
    if args.quick:
        args.res, args.faces, args.K = [400], [100_000], [30]
    print(f"{'scene':8} {'res':>5} {'faces':>8} {'K':>4} {'frag/px':>7} {'cover':>6} "
          f"{'fwd ms':>8} {'bwd ms':>8} {'total':>8} {'peak MiB':>9}")
    for scene in args.scenes:
        for M in args.faces:
            V, F = make_soup(scene, M)
            for res in args.res:
                for K in args.K:
                    if res * res * K * 40 > dev.info.max_alloc_bytes * 4:
                        print(f"{scene:8} {res:5d} {M:8d} {K:4d}  skipped: fragment buffers exceed device memory")
                        continue
                    ch = Chain(dev, V, F, camera(res), K)
                    try:
                        fwd = timed(ch.forward, args.runs)
                        bwd = timed(ch.backward, args.runs)
                    except MemoryError as exc:
                        print(f"{scene:8} {res:5d} {M:8d} {K:4d}  skipped: {exc}")
                        continue
                    fpp, cov = frag_stats(ch)
                    peak = dev.allocator.managed_bytes / 2**20 if hasattr(dev.allocator, "managed_bytes") else float("nan")
                    print(f"{scene:8} {res:5d} {M:8d} {K:4d} {fpp:7.1f} {cov:6.2f} {fwd:8.1f} {bwd:8.1f} "
                          f"{fwd + bwd:8.1f} {peak:9.0f}", flush=True)
                    dev.allocator.free_held()
    if not args.no_peer:
        # the opaque K=1 job on an 82k-face icosphere-like surface, 400²
        import trimesh

        ico = trimesh.creation.icosphere(subdivisions=6)  # 81,920 faces
        V = np.asarray(ico.vertices, np.float32)
        F = np.asarray(ico.faces, np.int32)
        cam = camera(400)
        ch = Chain(dev, V, F, cam, 1, sigma=1e6)
        ch.alv[:] = 1.0

        def ours():
            ch.forward()
            ch.backward()

        t_ours = timed(ours, args.runs)
        t_peer, what = mitsuba_opaque(V, F, ch.col, cam, args.runs)
        print(f"\nopaque job (K=1, per-vertex colour, {len(F)} faces, 400²), fwd+bwd median ms:")
        print(f"  triplet_cl: {t_ours:8.1f}")
        if t_peer is None:
            print(f"  mitsuba 3:  n/a — {what}")
        else:
            print(f"  mitsuba 3:  {t_peer:8.1f}  ({what})   ratio ours/mitsuba = {t_ours / t_peer:.2f}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
