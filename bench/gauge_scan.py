"""The albedo-light gauge of a capture (issue 18): what the level ``s`` (albedo × s, every light / s) changes, and
whether the photos themselves say which ``s`` is right.

Photos fix albedo × light; the level between them (the gauge) is not seen in the diffuse shading, only in a
dielectric's highlights (F0 = 0.04 whatever the albedo: a highlight's brightness is the light's alone) and, weakly,
in interreflection. Two scans, both diagnostics that read the ground truth only to score:

``run RUN RELIGHT``: the run's refined mesh at each ``s`` of ``--grid``: the training views' error (every pixel,
over white, as rendered by ``triplet eval``; albedo at 1 clips), the unscaled relight PSNR of every set and the
albedo PSNR (raw / per-channel scaled) with the truth / ours ratio; then the *specular* fit alone: with ``A`` the
mesh's render and ``B`` its render with albedo 0 (the highlights alone; no interreflection in either), the covered
pixels' error of ``(A − B) + B / s`` against the photos over a fine grid of ``s`` (no clipping of the albedo).

``gt SCENE``: the same specular fit on the ground-truth asset (``gt_mesh.obj`` subdivided twice, the texture
sampled per vertex, the truth's roughness and training lights, 4×4 supersampled): how sharply the highlights pin
the level when the geometry and the material are right.

    python bench/gauge_scan.py run RUN SCENE/relight [--grid 0.9,1,1.1,1.2,1.3] [--views 20]
    python bench/gauge_scan.py gt SCENE [--views 20]
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))  # bench/relight.py's gt_asset

FINE = np.exp(np.linspace(np.log(0.5), np.log(2.0), 25))  # the specular fit's levels


def specular_fit(A: np.ndarray, B: np.ndarray, P: np.ndarray) -> list[str]:
    """Rows of the specular fit: linear renders ``A`` (full) and ``B`` (specular alone), photos ``P`` (sRGB), all
    ``[n, 3]`` covered pixels; the error of ``(A − B) + B / s`` over every pixel and over the 5 % brightest
    highlights."""
    from triplet_cl.ops.color import srgb_encode

    hi = B.max(1) > np.percentile(B.max(1), 95)
    rows = [f"# specular fit: {len(A)} covered pixels, the highlights {B.sum() / max(A.sum(), 1e-12):.1%} of the "
            "linear radiance", "| s | MSE | PSNR (dB) | 5 % brightest highlights' MSE |", "|---|---|---|---|"]
    best = None
    for s in FINE:
        L = (A - B) + B / s
        e = float(np.mean((srgb_encode(np.clip(L, 0, 1)) - P) ** 2))
        eh = float(np.mean((srgb_encode(np.clip(L[hi], 0, 1)) - P[hi]) ** 2))
        rows.append(f"| {s:.3f} | {e:.4e} | {-10 * np.log10(e):.2f} | {eh:.4e} |")
        best = (s, e) if best is None or e < best[1] else best
    rows.append(f"# best s {best[0]:.3f}")
    return rows


def scan_run(run: Path, rdir: Path, grid: list[float], n_views: int) -> list[str]:
    from triplet_cl.activations import logit, sigmoid
    from triplet_cl.datasets.images import read_image
    from triplet_cl.lights import scale_lights, unpack_lights
    from triplet_cl.ops.color import srgb_decode
    from triplet_cl.relight import Relighter, albedo_psnr, load_light_sets
    from triplet_cl.train import Trainer, psnr

    tr = Trainer(None, run, resume=True, quiet=True)
    rl = Relighter(tr, "mesh")
    base = rl.base
    mat0 = np.asarray(base.material.data).copy()
    lp0 = np.asarray(base.light_params.data, np.float64).copy()
    lights0 = base.lights
    train, tests = rl.views("train")[:n_views], rl.views("test")
    doc = json.loads((rdir / "relight.json").read_text())
    sets = load_light_sets(rdir / "relight.json")

    def over_white(rgb, a):
        return rgb * a[..., None] + (1 - a[..., None])

    refs = {}
    for ls in sets:
        ims = [read_image(ls.images / f"{Path(v.name).name}.png") for v in tests]
        refs[ls.name] = [over_white(im.rgb, im.alpha) for im in ims]
    alb = [read_image(rdir / doc["albedo"] / f"{Path(v.name).name}.png") for v in tests]
    rows = [f"# {run}: {len(mat0)} vertices, lights {[type(lt).__name__ for lt in lights0]}, {len(train)} training "
            f"views, {len(tests)} test views", "| s | training MSE | albedo at 1 | relight " + " / ".join(
                ls.name for ls in sets) + " | albedo raw / scaled | truth / ours |", "|---|---|---|---|---|---|"]

    def set_level(s: float) -> float:
        a = sigmoid(mat0[:, 0:3].astype(np.float64)) * s
        mat = mat0.copy()
        mat[:, 0:3] = logit(np.clip(a, 1e-4, 1 - 1e-4)).astype(mat.dtype)
        base.material.data[...] = mat
        base.light_params.data[...] = scale_lights(lights0, lp0, 1.0 / s).astype(base.light_params.data.dtype)
        rl._vis.clear()
        rl._albedo_scene = None
        return float(np.mean(a.max(1) > 1 - 1e-4))

    for s in grid:
        sat = set_level(s)
        sc = rl.with_lights(unpack_lights(lights0, np.asarray(base.light_params.data, np.float64)))
        err = np.mean([np.mean((np.clip(rl.render(sc, v.camera, np.ones(3))[0], 0, 1) - over_white(v.rgb, v.alpha))
                               ** 2) for v in train])
        rel = []
        for ls in sets:
            scr = rl.with_lights(ls.lights)
            rel.append(np.mean([psnr(np.clip(rl.render(scr, v.camera, np.ones(3))[0], 0, 1), r)
                                for v, r in zip(tests, refs[ls.name], strict=True)]))
        preds = [rl.render_albedo(v.camera)[0] for v in tests]
        ap = albedo_psnr(np.stack(preds), np.stack([r.rgb for r in alb]), np.stack([r.alpha > 0.5 for r in alb]))
        rows.append(f"| {s:.2f} | {err:.4e} | {sat:.1%} | " + " / ".join(f"{x:.2f}" for x in rel)
                    + f" | {ap['psnr_raw']:.2f} / {ap['psnr_scaled']:.2f} | "
                    + " / ".join(f"{x:.2f}" for x in ap["scale"]) + " |")
        print(rows[-1], flush=True)
    set_level(1.0)
    sc = rl.with_lights(base.current_lights())
    A, P, msk = [], [], []
    for v in train:
        img, a = rl.render(sc, v.camera, np.zeros(3), bounce=False)
        m = (a > 0.999) & (v.alpha > 0.999)
        A.append(srgb_decode(np.clip(img[m], 0, 1)))
        P.append(v.rgb[m])
        msk.append(m)
    mat = mat0.copy()
    mat[:, 0:3] = logit(np.full((len(mat), 3), 1e-4)).astype(mat.dtype)
    base.material.data[...] = mat
    rl._vis.clear()
    sc0 = rl.with_lights(base.current_lights())
    B = [srgb_decode(np.clip(rl.render(sc0, v.camera, np.zeros(3), bounce=False)[0][m], 0, 1))
         for v, m in zip(train, msk, strict=True)]
    base.material.data[...] = mat0
    return rows + specular_fit(np.concatenate(A), np.concatenate(B), np.concatenate(P))


def scan_gt(scene: Path, n_views: int) -> list[str]:
    from relight import gt_asset  # a sibling script

    from triplet_cl.activations import logit
    from triplet_cl.datasets import load_dataset
    from triplet_cl.relight import parse_lights
    from triplet_cl.render import RenderSettings, render
    from triplet_cl.scene import Scene
    from triplet_cl.visibility import vertex_visibility

    V, F, mat0, gt = gt_asset(scene, Path("/work/shared/data/meshes"))
    n = len(V)

    def material(albedo):
        mat = mat0.copy()
        mat[:, 0:3] = logit(np.clip(albedo, 1e-4, 1 - 1e-4))
        return mat

    lights = parse_lights(gt["lights"], scene / "ground_truth.json")
    train = load_dataset(str(scene))["train"][:n_views]
    out = {}
    for key, albedo in (("A", None), ("B", np.zeros((n, 3)))):
        sc = Scene.from_arrays(V, F, material=mat0 if albedo is None else material(albedo),
                               alpha=np.full((n, 1), 30.0), lights=lights)
        vis = vertex_visibility(sc, ray_eps=0.01)
        imgs = []
        for v in train:
            st = RenderSettings(K=4, sigma=None, normals="vertex", background=(0, 0, 0), transfer=None)
            r = render(sc, v.camera.scaled(4), st, vis=vis)
            hh, ww = v.camera.height, v.camera.width
            imgs.append((r.image.reshape(hh, 4, ww, 4, 3).mean((1, 3)), r.alpha.reshape(hh, 4, ww, 4).mean((1, 3))))
        out[key] = imgs
    A, B, P = [], [], []
    for (ia, a), (ib, _), v in zip(out["A"], out["B"], train, strict=True):
        m = (a > 0.999) & (v.alpha > 0.999)
        A.append(ia[m])
        B.append(ib[m])
        P.append(v.rgb[m])
    return [f"# ground-truth asset of {scene}: {n} vertices, roughness {gt['roughness']}, lights "
            f"{[type(lt).__name__ for lt in lights]}, {len(train)} training views"] + specular_fit(
        np.concatenate(A), np.concatenate(B), np.concatenate(P))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = ap.add_subparsers(dest="cmd", required=True)
    r = sub.add_parser("run", help="a trained run's refined mesh")
    r.add_argument("run")
    r.add_argument("relight", help="the capture's relight folder (relight.json, albedo/)")
    r.add_argument("--grid", default="0.9,1,1.1,1.2,1.3,1.45", help="comma-separated levels s")
    r.add_argument("--views", type=int, default=20, help="training views used")
    g = sub.add_parser("gt", help="the ground-truth asset of a scene folder")
    g.add_argument("scene")
    g.add_argument("--views", type=int, default=20, help="training views used")
    ap.add_argument("--out", default=None, help="also append the rows to this file")
    args = ap.parse_args()
    t0 = time.perf_counter()
    if args.cmd == "run":
        rows = scan_run(Path(args.run), Path(args.relight), [float(x) for x in args.grid.split(",")], args.views)
    else:
        rows = scan_gt(Path(args.scene), args.views)
    rows.insert(0, f"# bench/gauge_scan.py {args.cmd} ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, "
                   f"{time.perf_counter() - t0:.0f} s)")
    print("\n".join(rows))
    if args.out:
        with open(args.out, "a") as fh:
            fh.write("\n".join(rows) + "\n\n")


if __name__ == "__main__":
    main()
