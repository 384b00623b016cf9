"""Training with the three renderers (issue 7): test PSNR, time per iteration, and whether the recovered
albedo is freer of baked-in shadows.

For each renderer (raster | hybrid | raytrace) the same :class:`~triplet_cl.train.TrainConfig` is run
on a NeRF-format scene rendered by a path tracer (default ``../shared/data/scenes/spot_small``), with
``TrainConfig.renderer`` (``RenderSettings.renderer``) set for every training and evaluation render.
Then the recovered soup's albedo is compared with the ground-truth texture:

* each opaque soup vertex (alpha > 0.5) within 2 % of the object size of the ground-truth surface
  takes the texture colour at its nearest point of the ground-truth mesh (dense surface samples,
  ``scipy.spatial.cKDTree``, UVs by barycentric interpolation);
* the ground-truth point light's cast shadows are found by tracing the ground-truth mesh with our own
  BVH (``ops.trace.shadow_forward``, opacity 1);
* among the points that face the light (N·L > 0), ``bias = mean log(albedo / texture)`` over the
  shadowed ones minus the same over the lit ones. A renderer that cannot explain a cast shadow paints it
  into the albedo (bias < 0); 0 means no baked shadow. Albedo MAE over all matched points is printed too.
Both images and texture are compared in their stored sRGB encoding (the trainer fits the PNGs as stored).

    python bench/raytrace_train.py --iterations 300
"""

from __future__ import annotations

import argparse
import dataclasses
import functools
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

import triplet_cl.train as train_mod
from triplet_cl import get_device
from triplet_cl.lights import PointLight, pack_lights
from triplet_cl.render import RenderSettings

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def gt_albedo_and_shadow(scene_dir: Path, points: np.ndarray, dev):
    """Texture colour [P, 3] at the nearest ground-truth surface point, distance [P], and whether that
    point faces the first ground-truth point light [P] and is in its cast shadow [P]."""
    import pyopencl.array as cla
    import trimesh
    from PIL import Image
    from scipy.spatial import cKDTree

    from triplet_cl.ops.bvh import build_bvh
    from triplet_cl.ops.mesh import DeviceMesh
    from triplet_cl.ops.trace import shadow_forward

    gt = json.loads((scene_dir / "ground_truth.json").read_text())
    mesh = trimesh.load(scene_dir / "gt_mesh.obj", process=False, force="mesh")
    tex = np.asarray(Image.open(DATA / "meshes" / "spot" / gt["texture"]).convert("RGB"), np.float64) / 255.0
    uv = np.asarray(mesh.visual.uv)
    samples, fid = trimesh.sample.sample_surface(mesh, 400_000, seed=0)
    bary = trimesh.triangles.points_to_barycentric(mesh.triangles[fid], samples)
    dist, idx = cKDTree(samples).query(points)
    f, b = fid[idx], bary[idx]
    suv = (uv[mesh.faces[f]] * b[..., None]).sum(1)
    h, w = tex.shape[:2]
    px = np.clip((suv[:, 0] * (w - 1)).round().astype(int), 0, w - 1)
    py = np.clip(((1 - suv[:, 1]) * (h - 1)).round().astype(int), 0, h - 1)
    colour = tex[py, px]
    light = [lt for lt in gt["lights"] if lt["type"] == "point"][0]
    q = np.asarray(light["position"], np.float64)
    n = mesh.face_normals[f]
    p = samples[idx]
    facing = ((q - p) * n).sum(1) > 0
    V = np.asarray(mesh.vertices, np.float32)
    F = np.asarray(mesh.faces, np.int32)
    dm = DeviceMesh(dev, F, len(V))
    bvh = build_bvh(dev, V, dm)
    table = pack_lights([PointLight(q, [1, 1, 1])])
    qd = dev.queue
    st = shadow_forward(dev, bvh, cla.to_device(qd, V), cla.to_device(qd, np.ones((len(V), 1), np.float32)), 0,
                        cla.to_device(qd, (p + 2e-3 * n).astype(np.float32)), cla.to_device(qd, f.astype(np.int32)),
                        cla.to_device(qd, table.ints), cla.to_device(qd, table.params.astype(np.float32)), table, 1e-4)
    shadowed = st.vis.get()[:, 0] < 0.5
    return colour, dist, facing, shadowed


def run(renderer: str, data: Path, iterations: int, out: Path, dev, gt_light: bool = False,
        ray_eps: float | None = None, downscale: int = 1) -> dict:
    wired = "renderer" in {f.name for f in dataclasses.fields(train_mod.TrainConfig)}
    # the trainer builds its RenderSettings itself: set the renderer through its config where it has the
    # field, and ray_eps (not a training option) by wrapping the settings class it uses
    extra = {} if ray_eps is None else {"ray_eps": ray_eps}
    if not wired:
        extra["renderer"] = renderer
    train_mod.RenderSettings = functools.partial(RenderSettings, **extra)
    try:
        cfg = train_mod.TrainConfig(iterations=iterations, seed=0, downscale=downscale,
                                    **({"renderer": renderer} if wired else {}))
        cfg.density.densify_until = min(cfg.density.densify_until, int(iterations * 0.8))
        tr = train_mod.Trainer(str(data), out / renderer, cfg, device=dev, quiet=True)
        if gt_light:  # start the (learned) point light at the ground-truth position
            gt = json.loads((data / "ground_truth.json").read_text())
            q = [lt for lt in gt["lights"] if lt["type"] == "point"][0]["position"]
            lp = tr.scene.light_params.data
            lp[0:3] = q  # lights ("point", "ambient"): the point light's position comes first
        t0 = time.perf_counter()
        tr.train()
        wall = time.perf_counter() - t0
        ev = tr.evaluate("test")
    finally:
        train_mod.RenderSettings = RenderSettings
    s = tr.scene
    sig = lambda x: 1 / (1 + np.exp(-x))  # noqa: E731
    alpha = sig(s.alpha.data[:, 0])
    alb = sig(s.material.data[:, :3])
    return {"renderer": renderer, "psnr": ev.get("psnr_mean", ev.get("psnr")), "s_per_it": wall / iterations,
            "faces": len(s.F), "V": s.V.data.astype(np.float64), "albedo": alb, "alpha": alpha}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--data", default=str(DATA / "scenes" / "spot_small"))
    ap.add_argument("--iterations", type=int, default=300)
    ap.add_argument("--renderers", nargs="*", default=["raster", "hybrid", "raytrace"])
    ap.add_argument("--ray-eps", type=float, default=None,
                    help="RenderSettings.ray_eps (× scene diagonal; default: RenderSettings' own)")
    ap.add_argument("--downscale", type=int, default=1, help="reduce the dataset's images by this factor")
    ap.add_argument("--gt-light", action="store_true", help="start the point light at the ground-truth position")
    args = ap.parse_args(argv)
    dev = get_device()
    data = Path(args.data)
    print(f"device: {dev.name}; data: {data}; {args.iterations} iterations"
          + ("; point light starts at the ground-truth position" if args.gt_light else "")
          + f"; ray_eps {args.ray_eps if args.ray_eps is not None else RenderSettings().ray_eps:g}"
          + (f"; images / {args.downscale}" if args.downscale > 1 else ""))
    print(f"{'renderer':9} {'test PSNR':>9} {'s/it':>6} {'faces':>6} {'albedo MAE':>10} {'shadow bias':>11} "
          f"{'(shadowed/lit pts)':>18}")
    with tempfile.TemporaryDirectory() as tmp:
        for r in args.renderers:
            res = run(r, data, args.iterations, Path(tmp), dev, args.gt_light, args.ray_eps, args.downscale)
            keep = res["alpha"] > 0.5
            colour, dist, facing, shadowed = gt_albedo_and_shadow(data, res["V"][keep], dev)
            near = dist < 0.02 * 2.0
            alb = res["albedo"][keep]
            mae = float(np.abs(alb[near] - colour[near]).mean())
            lr = np.log(np.clip(alb, 1e-3, 1)).mean(1) - np.log(np.clip(colour, 1e-3, 1)).mean(1)
            sh, lit = near & facing & shadowed, near & facing & ~shadowed
            bias = float(lr[sh].mean() - lr[lit].mean()) if sh.any() and lit.any() else float("nan")
            psnr = res["psnr"]
            print(f"{r:9} {psnr if psnr is not None else float('nan'):9.2f} {res['s_per_it']:6.2f} {res['faces']:6d} "
                  f"{mae:10.3f} {bias:11.3f} {int(sh.sum()):>8}/{int(lit.sum())}", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
