"""Mip-map bleed across UV-atlas charts as a function of the atlas padding (issue 21: dark speckles
in Eevee from lookups that average a chart's texels with another chart's gutter).

For each texel covered by a chart (what a renderer samples), mip level L (2^L × 2^L blocks of the
baked, gutter-filled texture) bleeds when its block also holds texels owned by another chart (a
gutter texel is owned by the chart of the covered texel its fill copies, as ``bake.bake`` does).
Reports the bleeding fraction per level, the atlas utilisation and the charts' texel count.

    .venv/bin/python bench/gutter.py [MESH.ply] [--size 1024] [--faces 50000] [--padding 2 4 8]
"""

from __future__ import annotations

import argparse
import time

import numpy as np
import trimesh

from triplet_cl.mesh.bake import gutter_sources, rasterize_uv, uv_atlas


def bleed(face_img: np.ndarray, chart: np.ndarray, levels=(1, 2, 3, 4), fill: str = "chart") -> dict[int, float]:
    """Bleeding fraction per mip level with the gutter filled as ``bake.bake`` does: ``"nearest"`` (the
    nearest covered texel of any chart) or ``"chart"`` (per chart, ``bake.gutter_sources``)."""
    covered = face_img >= 0
    own = np.full(face_img.shape, -1, np.int64)
    own[covered] = chart[face_img[covered]]
    iy, ix, _ = gutter_sources(face_img, chart if fill == "chart" else None)
    owner = own[iy, ix]
    h, w = owner.shape
    out = {}
    for lv in levels:
        b = 2**lv
        blk = owner[: h // b * b, : w // b * b].reshape(h // b, b, w // b, b).transpose(0, 2, 1, 3).reshape(
            h // b, w // b, b * b)
        mixed = (blk != blk[..., :1]).any(-1)  # the block holds more than one owner
        cov = covered[: h // b * b, : w // b * b].reshape(h // b, b, w // b, b).sum((1, 3))
        out[lv] = float((cov * mixed).sum() / max(cov.sum(), 1))
    return out


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("mesh", nargs="?", default="/work/shared/data/scenes/spot/gt_mesh.ply")
    ap.add_argument("--size", type=int, default=1024)
    ap.add_argument("--faces", type=int, default=50_000, help="simplify to this many faces first (0: keep)")
    ap.add_argument("--padding", type=int, nargs="+", default=[2, 4, 8])
    ap.add_argument("--fill", nargs="+", default=["nearest", "chart"], choices=["nearest", "chart"],
                    help="gutter fill: nearest covered texel (before) or per chart (bake's default now)")
    ap.add_argument("--voxel", type=float, default=0.0, help="remesh by marching cubes at this voxel size "
                    "(× the bounding-box diagonal) first: a mesh like the mesh stage's (0: keep)")
    a = ap.parse_args()
    m = trimesh.load(a.mesh, process=False, force="mesh")
    if a.voxel:
        m = m.voxelized(a.voxel * float(np.linalg.norm(m.extents))).fill().marching_cubes
    V, F = np.asarray(m.vertices), np.asarray(m.faces)
    if a.faces and len(F) > a.faces:
        s = m.simplify_quadric_decimation(face_count=a.faces)
        V, F = np.asarray(s.vertices), np.asarray(s.faces)
    print(f"{a.mesh}: {len(F)} faces, {a.size}² texture")
    print(f"{'padding':>7} {'fill':>7} {'charts':>6} {'util':>6} {'covered':>8} "
          + " ".join(f"{'mip' + str(lv):>7}" for lv in (1, 2, 3, 4, 5)) + "   seconds")
    for pad in a.padding:
        t0 = time.perf_counter()
        at = uv_atlas(V, F, a.size, pad)
        face_img, _ = rasterize_uv(at.uv, at.faces, a.size, a.size)
        chart = at.face_chart
        t_atlas = time.perf_counter() - t0
        for fill in a.fill:
            t1 = time.perf_counter()
            b = bleed(face_img, chart, (1, 2, 3, 4, 5), fill)
            print(f"{pad:7d} {fill:>7} {chart.max() + 1:6d} {at.utilization:6.3f} {(face_img >= 0).mean():8.3f} "
                  + " ".join(f"{b[lv]:7.3f}" for lv in (1, 2, 3, 4, 5))
                  + f"   {t_atlas + time.perf_counter() - t1:.1f}", flush=True)


if __name__ == "__main__":
    main()
