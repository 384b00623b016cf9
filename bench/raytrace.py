"""Benchmark of the ray tracer (issue 7): BVH build and refit, rays per second, the three renderers.

Per face count (thin-shell "surface" soups of bench/raster.py, faces in Morton order):
  build     Morton sort of the centroids + upload + first refit (ops/bvh.py), median ms
  refit     bottom-up refit after the positions moved (run after every optimiser step), median ms
  primary   camera rays keeping the K nearest hits (K = 30), Mrays/s
  shadow    one point light, a ray from every first-hit point (transmittance over all crossings), Mrays/s
  bounce    the mirror ray of every first-hit point (nearest hit), Mrays/s
  render    render() forward + backward (Cook-Torrance, point + ambient light, K = 30) for
            renderer = raster | hybrid | raytrace, median ms
Peer (when ``mitsuba`` imports with variant llvm_ad_rgb): the direct-illumination job on the same
mesh and camera — 1 spp, a point light, diffuse per-vertex colour, forward + backward
(d Σ image·v / d colour) with Mitsuba 3's ``direct`` integrator (one camera ray + one shadow ray per
pixel), next to ours doing the same job (K = 1, alpha 1, ``renderer="raytrace"``, no bounce).

    python bench/raytrace.py                 # 10k / 100k / 1M faces (1M at reduced resolution)
    python bench/raytrace.py --quick         # 10k and 100k at 200², no 1M
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time

import numpy as np
import pyopencl.array as cla

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from raster import camera, make_soup, timed  # noqa: E402  (bench/raster.py: same scenes)

from triplet_cl import get_device  # noqa: E402
from triplet_cl.lights import AmbientLight, PointLight, pack_lights  # noqa: E402
from triplet_cl.ops import trace as trace_op  # noqa: E402
from triplet_cl.ops.bvh import build_bvh, refit  # noqa: E402
from triplet_cl.ops.mesh import DeviceMesh  # noqa: E402
from triplet_cl.ops.raster import project  # noqa: E402
from triplet_cl.render import RenderSettings, render  # noqa: E402
from triplet_cl.scene import Scene  # noqa: E402

LIGHT = np.array([2.0, 2.5, 3.0])


def first_hits(dev, bvh, Vd, cam):
    """Shading points: the first hit of every covered pixel (positions, normals, faces) on the device."""
    vs = project(dev, Vd, cam)
    fr = trace_op.trace_primary(dev, bvh, Vd, vs, cam, 1)
    cnt = fr.count.get().reshape(-1)
    face = fr.face.get().reshape(-1)[cnt > 0]
    bary = fr.bary.get().reshape(-1, 2)[cnt > 0]
    V = Vd.get()
    F = bvh.mesh.faces[face]
    lam = np.concatenate([bary, 1 - bary.sum(1, keepdims=True)], 1)
    pos = (V[F] * lam[..., None]).sum(1)
    nrm = np.cross(V[F[:, 1]] - V[F[:, 0]], V[F[:, 2]] - V[F[:, 0]])
    q = dev.queue
    return (cla.to_device(q, pos.astype(np.float32)), cla.to_device(q, nrm.astype(np.float32)),
            cla.to_device(q, face.astype(np.int32)))


def ray_table(dev, M, res, runs, K=30):
    V, F = make_soup("surface", M)
    cam = camera(res)
    mesh = DeviceMesh(dev, F, len(V))
    q = dev.queue
    Vd = cla.to_device(q, V)
    t_build = timed(lambda: build_bvh(dev, V, mesh), runs)
    bvh = build_bvh(dev, V, mesh)
    V2 = V + np.random.default_rng(2).normal(0, 1e-3, V.shape).astype(np.float32)
    V2d = cla.to_device(q, V2)
    t_refit = timed(lambda: refit(dev, bvh, V2d), runs)
    refit(dev, bvh, Vd)
    vs = project(dev, Vd, cam)

    def primary():
        trace_op.trace_primary(dev, bvh, Vd, vs, cam, K)
        q.finish()

    t_prim = timed(primary, runs)
    pos, nrm, face = first_hits(dev, bvh, Vd, cam)
    P = pos.shape[0]
    attr = cla.to_device(q, np.full((len(V), 1), 0.5, np.float32))
    table = pack_lights([PointLight(LIGHT, [10, 10, 10])])
    lt_i, lt_f = cla.to_device(q, table.ints), cla.to_device(q, table.params.astype(np.float32))

    def shadow():
        trace_op.shadow_forward(dev, bvh, Vd, attr, 0, pos, face, lt_i, lt_f, table, 1e-4)
        q.finish()

    def bounce():
        trace_op.bounce(dev, bvh, Vd, pos, nrm, face, cam.center, True, 1e-4)
        q.finish()

    t_sh, t_bo = timed(shadow, runs), timed(bounce, runs)
    mr = lambda n, ms: n / ms / 1e3  # noqa: E731  Mrays/s
    return (f"{M:8d} {res:5d} {bvh.num_leaves:8d} {t_build:8.1f} {t_refit:8.1f} {mr(res * res, t_prim):9.2f} "
            f"{mr(P, t_sh):9.2f} {mr(P, t_bo):9.2f}")


def render_scene(V, F, brdf="cook_torrance", alpha=0.5, lights=None):
    n = len(V)
    rng = np.random.default_rng(3)
    mat = rng.normal(0, 0.5, (n, 6)).astype(np.float32)
    a = np.full((n, 1), math.log(alpha / (1 - alpha)) if alpha < 1 else 20.0, np.float32)
    lights = lights or [PointLight(LIGHT, [10, 10, 10]), AmbientLight([0.1, 0.1, 0.1])]
    return Scene.from_arrays(V, F, material=mat, alpha=a, lights=lights, brdf=brdf, dtype=np.float32)


def render_table(dev, M, res, runs):
    V, F = make_soup("surface", M)
    scene = render_scene(V, F)
    cam = camera(res)
    out = []
    for renderer in ("raster", "hybrid", "raytrace"):
        s = RenderSettings(K=30, sigma=1.0, renderer=renderer)
        v = np.random.default_rng(4).standard_normal((res, res, 3)).astype(np.float32)

        def step(s=s, v=v):
            scene.zero_grad()
            r = render(scene, cam, s, dev)
            r.backward(v)

        out.append(timed(step, runs))
    return f"{M:8d} {res:5d} " + " ".join(f"{t:9.1f}" for t in out)


def mitsuba_direct(V, F, col, cam, runs, v_img):
    """Mitsuba 3 llvm_ad_rgb: diffuse per-vertex colour, point light, ``direct`` integrator (1 emitter
    sample, 0 BSDF samples), 1 spp, forward + backward w.r.t. the vertex colours. (median ms, note)."""
    for lib in ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"):
        if "DRJIT_LIBLLVM_PATH" not in os.environ and os.path.exists(lib):
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
    try:
        import drjit as dr
        import mitsuba as mi

        mi.set_variant("llvm_ad_rgb")
    except Exception as exc:  # noqa: BLE001
        return None, f"mitsuba unavailable ({type(exc).__name__}: {exc})"
    H, W = cam.height, cam.width
    fov = math.degrees(2 * math.atan(W / 2 / cam.fx))
    c2w = cam.c2w.copy()
    c2w[:3, 0] *= -1  # OpenCV camera axes -> Mitsuba's (+X left, +Y up)
    c2w[:3, 1] *= -1
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "diffuse", "reflectance": {"type": "mesh_attribute", "name": "vertex_color"}})
    mesh = mi.Mesh("soup", len(V), len(F), props=props, has_vertex_normals=False, has_vertex_texcoords=False)
    mp = mi.traverse(mesh)
    V32, F32 = np.ascontiguousarray(V, np.float32), np.ascontiguousarray(F, np.uint32)
    mp["vertex_positions"] = dr.ravel(mi.Point3f(V32[:, 0], V32[:, 1], V32[:, 2]))
    mp["faces"] = dr.ravel(mi.Vector3u(F32[:, 0], F32[:, 1], F32[:, 2]))
    c = np.ascontiguousarray(col, np.float32)
    mesh.add_attribute("vertex_color", 3, dr.ravel(mi.Color3f(c[:, 0], c[:, 1], c[:, 2])))
    mp.update()
    scene = mi.load_dict({
        "type": "scene",
        "integrator": {"type": "direct", "emitter_samples": 1, "bsdf_samples": 0},
        "sensor": {"type": "perspective", "fov": fov, "fov_axis": "x", "to_world": mi.ScalarTransform4f(c2w),
                   "film": {"type": "hdrfilm", "width": W, "height": H, "pixel_format": "rgb",
                            "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent", "sample_count": 1}},
        "soup": mesh,
        "light": {"type": "point", "position": LIGHT.tolist(), "intensity": {"type": "rgb", "value": 10.0}},
    })
    sp = mi.traverse(scene)
    key = "soup.vertex_color"
    dr.enable_grad(sp[key])
    sp.update()
    v = mi.TensorXf(np.asarray(v_img, np.float32))

    def step():
        dr.set_grad(sp[key], 0)
        img = mi.render(scene, sp, spp=1, seed=0)
        loss = dr.sum(img * v, axis=None)
        dr.eval(img, loss)
        dr.backward(loss)
        dr.eval(dr.grad(sp[key]))
        dr.sync_thread()

    return timed(step, runs), f"llvm_ad_rgb direct, point light, 1 spp, {dr.thread_count()} threads"


def peer(dev, runs, res=400):
    import trimesh

    ico = trimesh.creation.icosphere(subdivisions=6)  # 81,920 faces, opaque
    V, F = np.asarray(ico.vertices, np.float32), np.asarray(ico.faces, np.int32)
    cam = camera(res)
    scene = render_scene(V, F, alpha=1.0 - 1e-6, lights=[PointLight(LIGHT, [10, 10, 10])])
    s = RenderSettings(K=1, sigma=None, renderer="raytrace", reflections=False, normals="vertex")
    v = np.random.default_rng(4).standard_normal((res, res, 3)).astype(np.float32)

    def ours():
        scene.zero_grad()
        render(scene, cam, s, dev).backward(v)

    t_ours = timed(ours, runs)
    col = np.random.default_rng(1).uniform(0, 1, (len(V), 3))
    t_peer, note = mitsuba_direct(V, F, col, cam, runs, v)
    print(f"\ndirect-illumination job ({len(F)} faces, {res}², 1 point light with shadow rays, fwd+bwd), median ms:")
    print(f"  triplet_cl raytrace: {t_ours:8.1f}  (K=1, Cook-Torrance; gradients of every parameter: positions, "
          "materials, alpha, light)")
    if t_peer is None:
        print(f"  mitsuba 3: n/a — {note}")
    else:
        print(f"  mitsuba 3:           {t_peer:8.1f}  ({note}; gradient w.r.t. vertex colours only)   "
              f"ratio ours/mitsuba = {t_ours / t_peer:.2f}")


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--runs", type=int, default=3)
    ap.add_argument("--quick", action="store_true", help="10k and 100k faces at 200², no 1M")
    ap.add_argument("--res", type=int, default=256)
    ap.add_argument("--res-1m", type=int, default=128, help="resolution for the 1M-face rows (2 CPU cores)")
    ap.add_argument("--no-peer", action="store_true")
    ap.add_argument("--no-render", action="store_true")
    args = ap.parse_args(argv)
    dev = get_device()
    print(f"device: {dev.name}  ({dev.info.type}, {dev.info.compute_units} CUs)")
    faces = [10_000, 100_000] if args.quick else [10_000, 100_000, 1_000_000]
    res = 200 if args.quick else args.res
    print(f"{'faces':>8} {'res':>5} {'leaves':>8} {'build ms':>8} {'refit ms':>8} {'prim Mr/s':>9} "
          f"{'shad Mr/s':>9} {'bnc Mr/s':>9}   (primary K=30)")
    for M in faces:
        t0 = time.perf_counter()
        print(ray_table(dev, M, args.res_1m if M >= 1_000_000 else res, args.runs), flush=True)
        dev.allocator.free_held()
        if time.perf_counter() - t0 > 600:
            print("  (stopping: the next size would take too long here)")
            break
    if not args.no_render:
        print(f"\nrender() forward + backward, K=30, median ms\n{'faces':>8} {'res':>5} {'raster':>9} {'hybrid':>9} "
              f"{'raytrace':>9}")
        for M in faces[:2]:
            print(render_table(dev, M, res, args.runs), flush=True)
            dev.allocator.free_held()
    if not args.no_peer:
        peer(dev, args.runs)
    return 0


if __name__ == "__main__":
    sys.exit(main())
