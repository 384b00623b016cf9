"""The ground truth's albedo sampled at a reconstructed mesh's vertices (issue 18): where the trained albedo stands
against what the same mesh would show with the truth's colours painted on it.

Each vertex of the run's refined mesh gets the ground truth's base colour, sampled (bilinearly) where the vertex
projects in the *test* views' albedo references (``RELIGHT/albedo/``) that see it (facing the camera, not
occluded, inside the reference's alpha; linear mean over those views); vertices no test view sees keep their trained
albedo. That mesh's albedo is rendered and scored exactly as ``triplet eval --relight`` does (``albedo_psnr``),
beside the trained albedo.

Not a ceiling: point samples of 200² references blur the colours (on spot and bob_env this row scores *below* the
trained albedo, which is fitted through the renderer's supersampled pixels). Where it scores far above the trained
albedo, the difference is the decomposition's, not the geometry's or the per-vertex representation's.

A diagnostic that reads the test views' ground truth on purpose (never an input of training):

    python bench/albedo_sampled.py RUN /work/shared/data/scenes/gadget/relight [--out bench/results/NAME.txt]
"""

from __future__ import annotations

import argparse
import json
import time
from pathlib import Path

import numpy as np


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="a run directory with a refined mesh (mesh_stage.npz)")
    ap.add_argument("relight", help="the scene's relight folder (relight.json, albedo/)")
    ap.add_argument("--out", default=None, help="also append the table to this file")
    args = ap.parse_args()

    from triplet_cl.datasets.images import read_image
    from triplet_cl.lights import PointLight
    from triplet_cl.mesh.bake import vertex_normals
    from triplet_cl.mesh.light_fit import vertex_observations
    from triplet_cl.ops.color import srgb_decode
    from triplet_cl.relight import Relighter, albedo_psnr
    from triplet_cl.scene import logit
    from triplet_cl.train import Trainer
    from triplet_cl.visibility import vertex_visibility

    t0 = time.perf_counter()
    run, rdir = Path(args.run), Path(args.relight)
    doc = json.loads((rdir / "relight.json").read_text())
    tr = Trainer(None, run, resume=True, quiet=True)
    rl = Relighter(tr, "mesh")
    views = rl.views("test")
    refs = []
    for v in views:
        im = read_image(rdir / doc["albedo"] / f"{Path(v.name).name}.png")
        refs.append((im.rgb, np.ones(im.rgb.shape[:2], np.float32) if im.alpha is None else im.alpha))

    def score() -> dict:
        rl._albedo_scene = None  # rebuilt from the base scene's current material
        preds = [rl.render_albedo(v.camera)[0] for v in views]
        return albedo_psnr(np.stack(preds), np.stack([r for r, _ in refs]), np.stack([a > 0.5 for _, a in refs]))

    scene = rl.base
    trained = score()
    V = np.asarray(scene.V.data, np.float64)
    normals = vertex_normals(V, scene.F)
    seen = vertex_visibility(scene, tr.device, lights=[PointLight(v.camera.center, np.ones(3)) for v in views],
                             ray_eps=rl.mesh_stage.cfg.shadow_eps, normals=normals)
    obs_views = [(v.camera, srgb_decode(np.clip(r, 0, 1)), a) for v, (r, a) in zip(views, refs, strict=True)]
    vi, _, val, _ = vertex_observations(V, normals, obs_views, seen)
    n = np.bincount(vi, minlength=len(V))
    got = n > 0
    mean = np.stack([np.bincount(vi, val[:, c], len(V)) for c in range(3)], 1) / np.maximum(n, 1)[:, None]
    mat = scene.material.data
    mat[got, 0:3] = logit(np.clip(mean[got], 1e-3, 1 - 1e-3)).astype(mat.dtype)
    sampled = score()
    lines = [f"# bench/albedo_sampled.py {run} {rdir}  {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}",
             f"# mesh: {len(V)} vertices, {len(scene.F)} faces; {int(got.sum())} vertices seen by a test view "
             f"({got.mean():.1%}), {n[got].mean():.1f} views each; {time.perf_counter() - t0:.0f} s",
             "| albedo per vertex | raw dB | scaled dB |", "|---|---|---|",
             f"| trained (the run's) | {trained['psnr_raw']:.2f} | {trained['psnr_scaled']:.2f} |",
             f"| the truth sampled at the vertices (not a ceiling) | {sampled['psnr_raw']:.2f} | "
             f"{sampled['psnr_scaled']:.2f} |"]
    text = "\n".join(lines)
    print(text)
    if args.out:
        with open(args.out, "a") as f:
            f.write(text + "\n")


if __name__ == "__main__":
    main()
