"""Benchmark of the whole rasterization chain, forward and backward (issue: rasterization).

Chain: project → bin → raster (K nearest) → interpolate (RGB + alpha) → coverage → composite, and
the adjoint back to vertex positions, colours, alphas and sigma. Median of ``--runs`` runs after a
warm-up, on the default device (``TRIPLET_DEVICE`` selects another).

Scenes (faces stored in Morton order of their centroids, as the training loop keeps them):
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
from triplet_cl.ops.blend import raster_blend, raster_blend_backward
from triplet_cl.ops.columns import copy_columns
from triplet_cl.ops.composite import composite, composite_backward, coverage
from triplet_cl.ops.interpolate import interpolate
from triplet_cl.ops.mesh import DeviceMesh
from triplet_cl.ops.raster import fragments_backward, project, project_backward, rasterize
from triplet_cl.topology import morton_order


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
    tri = c[:, None, :] + r * d
    tri = tri[morton_order(c)]  # faces in Morton order, as the training loop keeps its soup
    V = tri.reshape(-1, 3).astype(np.float32)
    F = np.arange(3 * M, dtype=np.int32).reshape(M, 3)
    return V, F


def camera(res: int) -> Camera:
    # sphere of radius 1 at distance 3.2 with a 40° field of view covers ~half the image
    return Camera.look_at([0.0, 0.0, 3.2], [0, 0, 0], [0, 1, 0], 40.0, res, res)


class Chain:
    """The renderer's raster path: one packed interpolation (RGB + alpha), coverage, compositing;
    backward through composite and the fused fragment adjoint to positions, colours, alphas, sigma."""

    def __init__(self, dev, V, F, cam, K, sigma=1.0):
        import pyopencl.array as cla

        self.dev, self.cam, self.K, self.sigma = dev, cam, K, sigma
        self.mesh = DeviceMesh(dev, F, len(V))
        rng = np.random.default_rng(1)
        self.col = rng.uniform(0, 1, (len(V), 3)).astype(np.float32)
        self.attr = np.concatenate([self.col, np.full((len(V), 1), 0.5, np.float32)], 1)
        q = dev.queue
        self.Vd = cla.to_device(q, V)
        self.attrd = cla.to_device(q, self.attr)
        self.v_img = cla.to_device(q, rng.standard_normal((cam.height, cam.width, 3)).astype(np.float32))
        v4 = np.zeros((cam.height, cam.width, 4), np.float32)  # RGB cotangent, 0 on the alpha channel
        v4[..., :3] = self.v_img.get()
        self.v_img4 = cla.to_device(q, v4)
        self.bg = np.ones(4)

    def set_alpha(self, a: float):
        self.attr[:, 3] = a
        self.attrd.set(self.attr)

    def forward(self):
        import pyopencl.array as cla

        d = self.dev
        self.vs = project(d, self.Vd, self.cam)
        self.fr = rasterize(d, self.vs, self.mesh, self.cam.width, self.cam.height, self.K, sigma=self.sigma)
        # colour + alpha in one interpolation; compositing reads channel 3 as alpha ("feat" C=4,
        # alpha taken from the same buffer through a view would need strides: composite 4 channels
        # with the alpha channel's own blend being harmless)
        self.fa = interpolate(d, self.attrd, self.fr)
        self.a = cla.empty(d.queue, (max(self.fr.P, 1), 1), np.float32, allocator=d.allocator)[: self.fr.P]
        copy_columns(d, self.fr, self.fa, 3, self.a, 0, 1)  # alpha = channel 3 (valid slots only)
        self.a = self.a.reshape(self.fr.P)
        self.win = coverage(d, self.fr, self.sigma)
        self.img, self.trans, self.ncon = composite(d, self.fr, self.fa, self.a, self.bg, win=self.win)
        d.queue.finish()

    def backward(self):
        d, fr = self.dev, self.fr
        vf, va, vw, _ = composite_backward(d, fr, self.fa, self.a, self.bg, self.ncon, self.trans, self.v_img4,
                                           win=self.win)
        copy_columns(d, fr, va.reshape(fr.P, 1), 0, vf, 3, 1, accumulate=True)  # + alpha's adjoint
        _, v_vs, _ = fragments_backward(d, fr, self.attrd, vf, v_win=vw, sigma=self.sigma)
        project_backward(d, self.Vd, self.cam, v_vs)
        d.queue.finish()


class FusedChain(Chain):
    """The same job through the fused per-vertex path (ops/blend.py): project → bin → one kernel for
    raster, interpolation, coverage and compositing; one per-tile adjoint pass, the per-entry
    gathers, and the projection's adjoint."""

    def forward(self):
        d = self.dev
        self.vs = project(d, self.Vd, self.cam)
        self.bl = raster_blend(d, self.vs, self.mesh, self.attrd, self.cam.width, self.cam.height, self.K,
                               bg=self.bg[:3], sigma=self.sigma)
        self.img, self.trans, self.fr = self.bl.image, self.bl.trans, self.bl  # frag_stats reads .count
        d.queue.finish()

    def backward(self):
        d = self.dev
        v_attr, v_vs, _ = raster_blend_backward(d, self.bl, self.v_img)
        project_backward(d, self.Vd, self.cam, v_vs)
        d.queue.finish()


CHAINS = {"generic": Chain, "fused": FusedChain}


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


def mitsuba_opaque(V, F, col, cam: Camera, runs: int, v_img=None, setup: str = "direct", ref=None):
    """Mitsuba 3 (llvm_ad_rgb) doing the opaque job: per-vertex colour, 1 spp, d(Σ image·v_img)/d(colour).

    ``setup``:
      direct   the ``direct`` integrator on a ``diffuse`` BSDF whose reflectance is the ``mesh_attribute``
               ``vertex_color``, lit by a ``constant`` emitter of radiance 1, one cosine-weighted BSDF
               sample and no emitter sample (``emitter_samples=0``): the escaping BSDF ray returns exactly
               albedo·1, so the image is the vertex colour without noise (the convex sphere never
               shadows itself). Cost per pixel: one camera ray + one BSDF ray.
      primary  the lower bound: the colour as the ``radiance`` of an ``area`` emitter, ``path`` integrator
               with ``max_depth=1`` (directly visible emission only): one camera ray per pixel.
    Both differentiate through ``mi.render`` + ``dr.backward`` (Mitsuba re-renders the primal with AD
    enabled in the backward pass; that is its documented way). Scene construction (Embree BVH) and the
    first call (LLVM compilation of the kernels) are outside the timing.

    ``v_img`` [H, W, 3] is the cotangent image (random if None). ``ref = (rgb [H,W,3], alpha [H,W],
    v_col [N,3])`` (ours) adds sanity numbers: silhouette IoU, mean |Δrgb| where both cover, the
    correlation of the colour gradients. Returns ``(median ms, description, checks)`` or
    ``(None, reason, {})`` when Mitsuba is unavailable or fails.
    """
    import os

    for lib in ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"):
        if "DRJIT_LIBLLVM_PATH" not in os.environ and os.path.exists(lib):
            os.environ["DRJIT_LIBLLVM_PATH"] = lib  # Debian's libllvm19 (drjit usually finds it anyway)
    try:
        import drjit as dr
        import mitsuba as mi

        mi.set_variant("llvm_ad_rgb")
    except Exception as exc:  # noqa: BLE001
        return None, f"mitsuba unavailable ({type(exc).__name__}: {exc})", {}
    try:
        return _mitsuba_opaque(dr, mi, V, F, col, cam, runs, v_img, setup, ref)
    except Exception as exc:  # noqa: BLE001
        return None, f"mitsuba failed ({type(exc).__name__}: {exc})", {}


def _mitsuba_opaque(dr, mi, V, F, col, cam, runs, v_img, setup, ref):
    H, W = cam.height, cam.width
    if abs(cam.fx - cam.fy) > 1e-6 * cam.fx or abs(cam.cx - W / 2) > 1e-6 or abs(cam.cy - H / 2) > 1e-6:
        raise ValueError("the Mitsuba peer needs fx = fy and a centred principal point")
    fov = math.degrees(2 * math.atan(W / 2 / cam.fx))
    # ours: OpenCV camera (+X right, +Y down, +Z forward); Mitsuba's: +X left, +Y up, +Z forward
    c2w = cam.c2w.copy()
    c2w[:3, 0] *= -1
    c2w[:3, 1] *= -1
    props = mi.Properties()
    colour = {"type": "mesh_attribute", "name": "vertex_color"}
    if setup == "direct":
        props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": colour})
        integrator = {"type": "direct", "emitter_samples": 0, "bsdf_samples": 1}
        extra = {"light": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}}}
        what = "llvm_ad_rgb, direct (diffuse × constant emitter, 1 BSDF ray), 1 spp"
    elif setup == "primary":
        props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.0}})
        props["emitter"] = mi.load_dict({"type": "area", "radiance": colour})
        integrator = {"type": "path", "max_depth": 1}
        extra = {}
        what = "llvm_ad_rgb, path max_depth=1 (emissive colour, camera rays only), 1 spp"
    else:
        raise ValueError(f"unknown setup {setup!r}")
    V = np.ascontiguousarray(V, np.float32)
    F = np.ascontiguousarray(F, np.uint32)
    col = np.ascontiguousarray(col, np.float32)
    mesh = mi.Mesh("soup", len(V), len(F), props=props, has_vertex_normals=False, has_vertex_texcoords=False)
    mp = mi.traverse(mesh)
    mp["vertex_positions"] = dr.ravel(mi.Point3f(V[:, 0], V[:, 1], V[:, 2]))
    mp["faces"] = dr.ravel(mi.Vector3u(F[:, 0], F[:, 1], F[:, 2]))
    mesh.add_attribute("vertex_color", 3, dr.ravel(mi.Color3f(col[:, 0], col[:, 1], col[:, 2])))
    mp.update()
    scene = mi.load_dict({
        "type": "scene",
        "integrator": integrator,
        "sensor": {"type": "perspective", "fov": fov, "fov_axis": "x", "to_world": mi.ScalarTransform4f(c2w),
                   "near_clip": cam.near, "far_clip": cam.far,
                   "film": {"type": "hdrfilm", "width": W, "height": H, "pixel_format": "rgba",
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 1}},
        "soup": mesh,
        **extra,
    })
    sp = mi.traverse(scene)
    key = "soup.vertex_color"
    dr.enable_grad(sp[key])
    sp.update()
    if v_img is None:
        v_img = np.random.default_rng(1).standard_normal((H, W, 3)).astype(np.float32)
    # cotangent on RGB; 0 on the alpha channel of the rgba film
    v = mi.TensorXf(np.concatenate([np.asarray(v_img, np.float32), np.zeros((H, W, 1), np.float32)], -1))
    out = {}

    def step():
        dr.set_grad(sp[key], 0)
        img = mi.render(scene, sp, spp=1, seed=0)
        loss = dr.sum(img * v, axis=None)
        dr.eval(img, loss)  # the primal image and loss are part of the job (drjit is lazy)
        dr.backward(loss)
        g = dr.grad(sp[key])
        dr.eval(g)
        dr.sync_thread()
        out["img"], out["g"] = img, g

    ms = timed(step, runs)
    checks = {"threads": dr.thread_count()}
    if ref is not None:
        rgb, alpha, v_col = ref
        im = np.asarray(out["img"], np.float32)
        mo, mm = np.asarray(alpha) > 0.5, im[..., 3] > 0.5
        both = mo & mm
        checks["iou"] = float((mo & mm).sum() / max(1, (mo | mm).sum()))
        d_rgb = np.abs(im[..., :3][both] - np.asarray(rgb)[both])
        checks["drgb"] = float(d_rgb.mean()) if both.any() else float("nan")
        if v_col is not None:
            g = np.asarray(out["g"], np.float32).ravel()  # ravelled [N, 3], like ours
            checks["gcorr"] = float(np.corrcoef(g, np.asarray(v_col, np.float32).ravel())[0, 1])
    return ms, what, checks


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=5)
    ap.add_argument("--quick", action="store_true", help="only 400², 100k faces, K=30 and the peer")
    ap.add_argument("--res", type=int, nargs="*", default=[200, 400, 800])
    ap.add_argument("--faces", type=int, nargs="*", default=[10_000, 100_000, 1_000_000])
    ap.add_argument("--K", type=int, nargs="*", default=[1, 30, 150])
    ap.add_argument("--scenes", nargs="*", default=["surface", "dense"])
    ap.add_argument("--chain", choices=["generic", "fused", "both"], default="both",
                    help="generic: rasterize → interpolate → coverage → composite (the deferred-shading path); "
                         "fused: ops/blend.py (per-vertex attributes)")
    ap.add_argument("--no-peer", action="store_true")
    args = ap.parse_args(argv)
    dev = get_device()
    print(f"device: {dev.name}  ({dev.info.type}, {dev.info.compute_units} CUs)")
    if args.quick:
        args.res, args.faces, args.K = [400], [100_000], [30]
    chains = list(CHAINS) if args.chain == "both" else [args.chain]
    print(f"{'scene':8} {'res':>5} {'faces':>8} {'K':>4} {'chain':>8} {'frag/px':>7} {'cover':>6} "
          f"{'fwd ms':>8} {'bwd ms':>8} {'total':>8} {'peak MiB':>9}")
    for scene in args.scenes:
        for M in args.faces:
            V, F = make_soup(scene, M)
            for res in args.res:
                for K in args.K:
                    if res * res * K * 40 > dev.info.max_alloc_bytes * 4:
                        print(f"{scene:8} {res:5d} {M:8d} {K:4d}  skipped: fragment buffers exceed device memory")
                        continue
                    for name in chains:
                        ch = None
                        dev.allocator.free_held()  # the previous configuration's buffers go back first
                        ch = CHAINS[name](dev, V, F, camera(res), K)
                        try:
                            fwd = timed(ch.forward, args.runs)
                            bwd = timed(ch.backward, args.runs)
                        except MemoryError as exc:
                            print(f"{scene:8} {res:5d} {M:8d} {K:4d} {name:>8}  skipped: {exc}")
                            continue
                        fpp, cov = frag_stats(ch)
                        # device memory the pooled allocator holds after a forward + backward (≈ the peak)
                        peak = getattr(dev.allocator, "managed_bytes", float("nan")) / 2**20
                        print(f"{scene:8} {res:5d} {M:8d} {K:4d} {name:>8} {fpp:7.1f} {cov:6.2f} {fwd:8.1f} "
                              f"{bwd:8.1f} {fwd + bwd:8.1f} {peak:9.0f}", flush=True)
                        dev.allocator.free_held()
    if not args.no_peer:
        # the opaque K=1 job on an 82k-face icosphere, 400²: hard coverage (sigma huge), alpha 1
        import trimesh

        ico = trimesh.creation.icosphere(subdivisions=6)  # 81,920 faces
        V = np.asarray(ico.vertices, np.float32)
        F = np.asarray(ico.faces, np.int32)
        cam = camera(400)
        ours_ms = {}
        for name in chains:
            # hard coverage: the generic chain with a window so sharp it is a step (sigma 1e6), the fused path
            # with no window at all (sigma None)
            ch = CHAINS[name](dev, V, F, cam, 1, sigma=1e6 if name == "generic" else None)
            ch.set_alpha(1.0)

            def ours(ch=ch):
                ch.forward()
                ch.backward()

            ours_ms[name] = timed(ours, args.runs)

        # sanity numbers from the fused path (its image and colour gradient equal the generic chain's: tests)
        fz = FusedChain(dev, V, F, cam, 1, sigma=None)
        fz.set_alpha(1.0)
        fz.forward()
        v_attr, _, _ = raster_blend_backward(dev, fz.bl, fz.v_img)
        ref = (fz.img.get()[..., :3], fz.bl.alpha, v_attr.get()[:, :3])
        print(f"\nopaque job (K=1, per-vertex colour, {len(F)} faces, 400², d/d colours), fwd+bwd median ms:")
        for name, t in ours_ms.items():
            print(f"  triplet_cl ({name}): {t:8.1f}  (also computes the gradients w.r.t. positions and alphas)")
        for setup in ("direct", "primary"):
            t_peer, what, chk = mitsuba_opaque(V, F, fz.col, cam, args.runs, v_img=fz.v_img.get(), setup=setup,
                                               ref=ref)
            if t_peer is None:
                print(f"  mitsuba 3:  n/a — {what}")
                break
            ratios = ", ".join(f"{name} {t / t_peer:.2f}" for name, t in ours_ms.items())
            print(f"  mitsuba 3:  {t_peer:8.1f}  ({what}, {chk['threads']} threads)   ratio ours/mitsuba: {ratios}")
            gc = f"{chk['gcorr']:.3f}" if "gcorr" in chk else "n/a"
            print(f"    sanity: silhouette IoU {chk['iou']:.4f}, mean |Δrgb| where both cover {chk['drgb']:.3f} "
                  f"(Mitsuba jitters its sample in the pixel), colour-gradient correlation {gc}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
