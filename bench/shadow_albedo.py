"""Benchmark: how much of a run's albedo error sits in the training light's cast shadows.

Usage::

    python bench/shadow_albedo.py SCENE_DIR RUN [RUN ...]

For each test view the ground-truth mesh (``gt_mesh.obj``) gives a shadow mask: the per-vertex visibility
towards the training light of ``ground_truth.json`` (``visibility.vertex_visibility`` on the mesh, rendered
through the test camera) below 0.5 at facing surface points. Each run's rendered albedo (as
``triplet eval --relight``: raster, base colour) is compared with ``relight/albedo/`` after the per-channel
scale fitted over all covered pixels (``relight.albedo_psnr``), and the PSNR is split into shadowed and lit
pixels: if the photos' shadows were painted into the albedo, the shadowed pixels are the worse ones.
"""

from __future__ import annotations

import json
import math
import sys
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))


def shadow_masks(scene_dir: Path, views):
    import trimesh

    from triplet_cl.lights import AmbientLight, PointLight
    from triplet_cl.materials import colour_display_raw
    from triplet_cl.render import RenderSettings, render
    from triplet_cl.scene import Scene, logit
    from triplet_cl.visibility import vertex_visibility

    gt = json.loads((scene_dir / "ground_truth.json").read_text())
    m = trimesh.load(scene_dir / "gt_mesh.obj", process=False)
    V, F = np.asarray(m.vertices, np.float64), np.asarray(m.faces)
    n = len(V)
    L = [lt for lt in gt["lights"] if lt["type"] == "point"][0]
    pos = np.asarray(L["position"], np.float64)
    sc = Scene.from_arrays(V, F, material=np.zeros((n, 6)), alpha=np.full((n, 1), 30.0),
                           lights=[PointLight(pos, np.ones(3))])
    vis = vertex_visibility(sc, ray_eps=0.01)[:, 0]
    # facing the light (vertex normals of the mesh): N·L <= 0 is dark anyway, not a cast shadow
    facing = (np.asarray(m.vertex_normals) * (pos - V)).sum(1) > 0
    shade = np.where(facing, vis, 1.0)
    # shown exactly by an ambient light of 1 (as triplet_cl.relight's albedo renders)
    mat = colour_display_raw(logit(np.clip(np.repeat(shade[:, None], 3, 1), 1e-4, 1 - 1e-4)))
    show = Scene.from_arrays(V, F, material=mat, alpha=np.full((n, 1), 30.0), lights=[AmbientLight(np.ones(3))],
                             brdf="blinn_phong")
    out = []
    for v in views:
        r = render(show, v.camera, RenderSettings(K=4, sigma=None, normals="vertex", background=(1, 1, 1)))
        out.append((r.image[..., 0] < 0.5) & (r.alpha > 0.5))
    return out


def main() -> None:
    from triplet_cl.datasets.images import read_image
    from triplet_cl.ops.color import srgb_decode, srgb_encode
    from triplet_cl.relight import Relighter
    from triplet_cl.train import Trainer

    scene_dir = Path(sys.argv[1])
    masks = None
    print("| run | albedo scaled, all | in the cast shadows | lit | shadowed pixels |")
    print("|---|---|---|---|---|")
    for run in sys.argv[2:]:
        tr = Trainer(None, run, resume=True, quiet=True)
        rl = Relighter(tr, "soup")
        views = rl.views("test")
        if masks is None:
            masks = shadow_masks(scene_dir, views)
        P, G, S = [], [], []
        for v, sm in zip(views, masks, strict=True):
            pred, _ = rl.render_albedo(v.camera)
            im = read_image(scene_dir / "relight" / "albedo" / f"{Path(v.name).name}.png")
            cov = im.alpha > 0.5
            P.append(pred[cov]), G.append(im.rgb[cov]), S.append(sm[cov])
        p, g, s = np.concatenate(P), np.concatenate(G), np.concatenate(S)
        pl, gl = srgb_decode(np.clip(p, 0, 1)), srgb_decode(np.clip(g, 0, 1))
        scale = (pl * gl).sum(0) / np.maximum((pl * pl).sum(0), 1e-12)
        err = (np.clip(srgb_encode(np.clip(pl * scale, 0, 1)), 0, 1) - g) ** 2

        def ps(sel, err=err):
            return 10 * math.log10(1 / float(err[sel].mean()))

        print(f"| {run} | {ps(np.ones(len(s), bool)):.2f} | {ps(s):.2f} | {ps(~s):.2f} | {s.mean() * 100:.1f} % |")


if __name__ == "__main__":
    main()
