"""Benchmark of the PBR asset export (issue 8): time per stage and file sizes for a ~100k-face mesh.

Mesh: the shared ``scenes/spot/gt_mesh.obj`` midpoint-subdivided twice (93 696 faces), its per-vertex
albedo sampled from the ground-truth texture at the subdivided UVs (so the baked PNGs compress like
a real asset's), smooth roughness / metallic / AO fields, a point light and a degree-2 SH environment.
One run per texture size (the stages are deterministic host code; xatlas dominates).

    python bench/export.py                       # texture 1024 and 2048
    python bench/export.py --sizes 512 --out /tmp/export_bench
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"


def bench_asset(data: Path = DATA):
    import trimesh
    from PIL import Image

    from triplet_cl.lights import PointLight, SHEnvironmentLight
    from triplet_cl.mesh import MeshAsset

    m = trimesh.load(data / "scenes" / "spot" / "gt_mesh.obj", process=False)
    V, F, uv = np.asarray(m.vertices), np.asarray(m.faces), np.asarray(m.visual.uv)
    for _ in range(2):
        V, F, attrs = trimesh.remesh.subdivide(V, F, vertex_attributes={"uv": uv})
        uv = attrs["uv"]
    tex = np.asarray(Image.open(data / "meshes" / "spot" / "spot_texture.png").convert("RGB"), np.float64) / 255
    h, w = tex.shape[:2]
    px = np.clip((uv[:, 0] % 1) * w, 0, w - 1).astype(int)
    py = np.clip((1 - uv[:, 1] % 1) * h, 0, h - 1).astype(int)
    c = V - V.mean(0)
    attrs = {"albedo": tex[py, px], "roughness": 0.5 + 0.3 * np.tanh(c[:, 1]), "metallic": 0.2 + 0.1 * np.tanh(c[:, 0]),
             "ao": 0.8 + 0.15 * np.tanh(c[:, 2]), "alpha": np.ones(len(V))}
    coeffs = np.zeros((3, 9))
    coeffs[:, 0] = 2.0
    coeffs[:, 2] = 0.5
    return MeshAsset(V, F, attrs, lights=[PointLight([0, 3, 1], [5, 5, 5]), SHEnvironmentLight(coeffs)])


def main(argv=None):
    from triplet_cl.mesh.bake import rasterize_uv, uv_atlas
    from triplet_cl.mesh.export import bake_asset, export_asset

    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--sizes", type=int, nargs="+", default=[1024, 2048])
    ap.add_argument("--out", type=Path, default=None, help="keep the files here (default: a temporary folder)")
    args = ap.parse_args(argv)
    asset = bench_asset()
    print(f"mesh: {asset.num_vertices} vertices, {asset.num_faces} faces")
    for s in args.sizes:
        t0 = time.perf_counter()
        atlas = uv_atlas(asset.V, asset.F, s)
        t_atlas = time.perf_counter() - t0
        t0 = time.perf_counter()
        face, _ = rasterize_uv(atlas.uv, atlas.faces, s, s)
        t_rast = time.perf_counter() - t0
        t0 = time.perf_counter()
        bake_asset(asset, s)
        t_bake = time.perf_counter() - t0
        with tempfile.TemporaryDirectory() as tmp:
            out = (args.out / str(s)) if args.out else Path(tmp)
            t0 = time.perf_counter()
            paths = export_asset(asset, out, texture_size=s)
            t_all = time.perf_counter() - t0
            sizes = {p.name: p.stat().st_size for p in sorted(out.iterdir())}
        print(f"texture {s}: atlas {t_atlas:.1f} s ({atlas.charts} charts, {len(atlas.uv)} atlas vertices, "
              f"utilization {atlas.utilization:.2f}, {100 * (face >= 0).mean():.0f}% texels covered), "
              f"UV raster {t_rast:.2f} s, bake_asset (atlas + raster + bake) {t_bake:.1f} s, "
              f"export_asset (glb+obj+ply+envmap) {t_all:.1f} s")
        print("   sizes: " + ", ".join(f"{k} {v / 1e6:.2f} MB" for k, v in sizes.items()))
        del paths


if __name__ == "__main__":
    main()
