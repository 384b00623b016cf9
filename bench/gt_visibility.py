"""How much of a scene's ``gt_mesh.ply`` any view sees, and how a mesh's completeness splits between the seen and
the unseen part (issue 19: gadget is built of overlapping primitives, so its gt holds internal faces and an
underside no camera sees; a reconstruction of the visible surface cannot approach those).

A gt sample is *seen* when, in some training or test view, it projects onto the gt's own rendered surface (the
depth of the gt mesh rendered opaque by our rasterizer, ``mesh.extract.render_depth``) no deeper than ``--tol``.

    .venv/bin/python bench/gt_visibility.py SCENE_DIR [MESH ...] [--tol 0.015] [--samples 200000]

Prints the seen fraction, and per mesh: completeness (gt → mesh mean distance) over all / seen / unseen samples,
and the Chamfer distance's part that the unseen samples alone contribute, (unseen share × their mean) / 2.
"""

from __future__ import annotations

import argparse

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene")
    ap.add_argument("meshes", nargs="*")
    ap.add_argument("--tol", type=float, default=0.015, help="depth tolerance (world units)")
    ap.add_argument("--samples", type=int, default=200_000)
    a = ap.parse_args()

    import trimesh
    from scipy.spatial import cKDTree

    from triplet_cl.datasets import load_dataset
    from triplet_cl.device import get_device
    from triplet_cl.mesh.extract import _project_voxels, render_depth
    from triplet_cl.scene import Scene, logit

    gt = trimesh.load(f"{a.scene}/gt_mesh.ply", process=False)
    V = np.asarray(gt.vertices)[np.asarray(gt.faces)].reshape(-1, 3)
    soup = Scene.from_arrays(V, np.arange(len(V)).reshape(-1, 3), alpha=np.full((len(V), 1), logit(0.999)))
    ds = load_dataset(a.scene)
    pg, _ = trimesh.sample.sample_surface(gt, a.samples, seed=0)
    seen = np.zeros(len(pg), bool)
    dev = get_device()
    views = list(ds.train) + list(ds["test"] or [])
    for v in views:
        depth, acc = render_depth(soup, v.camera, K=4, sigma=None, mode="quantile", quantile=0.5, device=dev)
        idx, pix, z = _project_voxels(pg.astype(np.float32), v.camera)
        ok = (acc.reshape(-1)[pix] > 0.5) & (z <= depth.reshape(-1)[pix] + a.tol)
        seen[idx[ok]] = True
    print(f"{a.scene}: {seen.mean():.3f} of gt_mesh's surface seen by the {len(views)} views (tol {a.tol})")
    for path in a.meshes:
        m = trimesh.load(path, process=False)
        ps, _ = trimesh.sample.sample_surface(m, a.samples, seed=1)
        d21 = cKDTree(ps).query(pg)[0]
        floor = (~seen).mean() * d21[~seen].mean() / 2
        print(f"{path}: completeness all {d21.mean():.5f}, seen {d21[seen].mean():.5f}, "
              f"unseen {d21[~seen].mean():.5f}; the unseen samples' part of the Chamfer distance {floor:.5f}")


if __name__ == "__main__":
    main()
