"""Albedo of an exported GLB against the ground-truth texture (issue 8, "albedo error where it can be
compared"), and how much the texture bake itself loses.

From a training run: the latest checkpoint's soup → :func:`~triplet_cl.mesh.extract.extract_mesh`
(TSDF) → :func:`~triplet_cl.mesh.export.export_asset` → the GLB read back with trimesh. Then, at
``--points`` area-uniform samples of the ground-truth mesh (``gt_mesh.obj``, UVs into the scene's
texture named in ``ground_truth.json``):

* ``gt``      the ground-truth albedo (texture, bilinear; sRGB values as stored),
* ``texture`` the GLB's base-colour texture at the closest point of the exported mesh (nearest of
  ``--dense`` area-uniform samples of it),
* ``vertex``  the asset's per-vertex albedo interpolated at that same closest point.

Reported: ``texture`` vs ``gt`` (MAE, PSNR; also after the per-channel least-squares scale that
removes the albedo/light-intensity ambiguity) and ``texture`` vs ``vertex`` (the bake's own error).
The run directory is copied to a temporary folder first (nothing is written into it).

    python bench/export_quality.py /work/runs/spot --texture 1024
    python bench/export_quality.py runs/spot --refined        # the mesh of `triplet extract runs/spot`
"""

from __future__ import annotations

import argparse
import json
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np


def _bilinear(img: np.ndarray, uv_up: np.ndarray) -> np.ndarray:
    """``img [H, W, C]`` at UVs with v up (trimesh / OBJ convention), bilinear, clamped to the edge."""
    h, w = img.shape[:2]
    x = np.clip(uv_up[:, 0] * w - 0.5, 0, w - 1)
    y = np.clip((1 - uv_up[:, 1]) * h - 0.5, 0, h - 1)
    x0, y0 = np.minimum(np.floor(x).astype(int), w - 2), np.minimum(np.floor(y).astype(int), h - 2)
    fx, fy = (x - x0)[:, None], (y - y0)[:, None]
    return ((1 - fx) * (1 - fy) * img[y0, x0] + fx * (1 - fy) * img[y0, x0 + 1]
            + (1 - fx) * fy * img[y0 + 1, x0] + fx * fy * img[y0 + 1, x0 + 1])


def _samples(V, F, n, seed):
    """``n`` area-uniform surface samples as (face ``[n]``, barycentrics ``[n, 3]``)."""
    tri = V[F]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    rng = np.random.default_rng(seed)
    face = rng.choice(len(F), size=n, p=area / area.sum())
    s, r2 = np.sqrt(rng.random(n)), rng.random(n)
    return face, np.stack([1 - s, s * (1 - r2), s * r2], 1)


def _psnr(a, b) -> float:
    return float(10 * np.log10(1.0 / np.mean((a - b) ** 2)))


def main(argv=None):
    import trimesh
    from PIL import Image
    from scipy.spatial import cKDTree

    from triplet_cl.mesh.export import export_asset
    from triplet_cl.mesh.extract import extract_mesh
    from triplet_cl.train import Trainer

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("run", type=Path)
    ap.add_argument("--texture", type=int, default=1024)
    ap.add_argument("--points", type=int, default=20000)
    ap.add_argument("--dense", type=int, default=2_000_000, help="samples of the export for the closest points")
    ap.add_argument("--resolution", type=int, default=128, help="TSDF grid")
    ap.add_argument("--out", type=Path, default=None, help="keep the exported files here")
    ap.add_argument("--refined", action="store_true", help="use the run's refined mesh (mesh_stage.npz of "
                    "`triplet extract`) instead of extracting the soup")
    args = ap.parse_args(argv)

    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / "run"
        (run / "checkpoints").mkdir(parents=True)
        shutil.copy(args.run / "config.json", run / "config.json")
        latest = (args.run / "checkpoints" / "latest").read_text().strip()
        shutil.copy(args.run / "checkpoints" / latest, run / "checkpoints" / latest)
        (run / "checkpoints" / "latest").write_text(latest)
        tr = Trainer(None, run, resume=True, quiet=True)
        data = Path(tr.data)
        t0 = time.perf_counter()
        if args.refined:
            from triplet_cl.mesh.asset import MeshAsset
            from triplet_cl.mesh.refine import MESH_STATE, load_mesh_state

            asset = MeshAsset.from_scene(load_mesh_state(args.run / MESH_STATE))
        else:
            asset = extract_mesh(tr.scene, [v.camera for v in tr.ds.train], "tsdf", resolution=args.resolution)
        t_extract = time.perf_counter() - t0
        out = args.out or Path(tmp) / "export"
        t0 = time.perf_counter()
        from triplet_cl.mesh.refine import albedo_space

        paths = export_asset(asset, out, formats=("glb",), texture_size=args.texture,
                             albedo_space=albedo_space(tr.cfg.color))  # linear-pipeline albedo: sRGB-encoded
        t_export = time.perf_counter() - t0
        scene = trimesh.load(paths["glb"], process=False)
        g = list(scene.geometry.values())[0]
        base = np.asarray(g.visual.material.baseColorTexture.convert("RGB"), np.float64) / 255

    gt_info = json.loads((data / "ground_truth.json").read_text())
    gt = trimesh.load(data / "gt_mesh.obj", process=False)
    tex_path = next((data.parents[1] / "meshes").rglob(gt_info["texture"]))
    gt_tex = np.asarray(Image.open(tex_path).convert("RGB"), np.float64) / 255
    Vg, Fg, UVg = np.asarray(gt.vertices), np.asarray(gt.faces), np.asarray(gt.visual.uv)
    tri, w = _samples(Vg, Fg, args.points, seed=0)
    pts = np.einsum("nk,nkd->nd", w, Vg[Fg[tri]])
    gt_alb = _bilinear(gt_tex, np.einsum("nk,nkd->nd", w, UVg[Fg[tri]]) % 1.0)

    # closest point on the export: nearest of a dense area-uniform sampling of the GLB's mesh
    Ve, Fe, UVe = np.asarray(g.vertices, np.float64), np.asarray(g.faces), np.asarray(g.visual.uv)
    tri2, w2 = _samples(Ve, Fe, args.dense, seed=1)
    dense = np.einsum("nk,nkd->nd", w2, Ve[Fe[tri2]])
    dist, j = cKDTree(dense).query(pts, workers=-1)
    tri2, w2 = tri2[j], w2[j]
    tex_alb = _bilinear(base, np.einsum("nk,nkd->nd", w2, UVe[Fe[tri2]]))
    # the asset's per-vertex albedo at the same point (GLB vertices are asset vertices split at seams)
    vmap = cKDTree(asset.V).query(Ve)[1]
    vert_alb = np.einsum("nk,nkd->nd", w2, asset.attributes["albedo"][vmap[Fe[tri2]]].astype(np.float64))

    scale = (tex_alb * gt_alb).sum(0) / (tex_alb * tex_alb).sum(0)
    print(f"run {args.run}: extracted {asset.num_vertices} vertices / {asset.num_faces} faces in {t_extract:.1f} s, "
          f"GLB ({args.texture}²) in {t_export:.1f} s; {args.points} GT samples, mean distance to the export "
          f"{dist.mean():.4f}")
    print(f"  texture vs GT albedo:  MAE {np.abs(tex_alb - gt_alb).mean():.4f}, PSNR {_psnr(tex_alb, gt_alb):.2f} dB; "
          f"after per-channel scale {np.round(scale, 3).tolist()}: MAE "
          f"{np.abs(scale * tex_alb - gt_alb).mean():.4f}, PSNR {_psnr(np.clip(scale * tex_alb, 0, 1), gt_alb):.2f} dB")
    print(f"  vertex vs GT albedo:   MAE {np.abs(vert_alb - gt_alb).mean():.4f}, PSNR {_psnr(vert_alb, gt_alb):.2f} dB")
    print(f"  texture vs vertex (the bake's own error): MAE {np.abs(tex_alb - vert_alb).mean():.4f}, "
          f"max {np.abs(tex_alb - vert_alb).max():.4f}, PSNR {_psnr(tex_alb, vert_alb):.2f} dB")


if __name__ == "__main__":
    main()
