"""Relighting table of the dev scenes (issue 17): per run and stage (soup, mesh), the novel-view PSNR, the relit
PSNR of each light set of ``scenes/<scene>/relight/`` and the albedo PSNR (raw / per-channel scaled), and the
training time; optionally the relit images of one view beside the ground truth.

Runs are folders named after their scene under each ``--runs LABEL=FOLDER`` (e.g. ``before=/tmp/runs_before``):
``FOLDER/<scene>`` (the demo run may be ``spot_small``). A run whose ``metrics.json`` has no ``"relight"``
section (or with ``--force``) is evaluated first with ``triplet eval RUN --relight DIR``.

    python bench/relight.py --runs before=/tmp/runs_before after=/tmp/runs_after --scenes spot_small,spot,bob_env \\
        --images bench/results
    python bench/relight.py --gt-ceiling spot_small --env-degrees 0,1,2,4,8   # our renderer on the true mesh+material

``--gt-ceiling`` relights the ground-truth mesh (``gt_mesh.obj``, subdivided twice) with the ground-truth material
(texture decoded to linear, ``roughness``/``metallic`` of ``ground_truth.json``) with our renderer: what the
renderer itself can reach (no shadows in raster, no inter-reflection), and a check of the light-file conventions
and of the environment's SH degree. It reads ``ground_truth.json`` to check, never to train.

``--lights`` adds the recovered lights against ``ground_truth.json`` per run (issue 18): for each true point light
the recovered point light nearest in direction (seen from the object's centre, the origin of the dev scenes) with
its position error, direction error (degrees), intensity ratio and irradiance ratio at the centre (``I / d²``, the
quantity the photos fix; the intensity alone trades against the distance); a recovered directional light is
compared by direction and irradiance. The ambient (or SH environment's band 0) radiance is set against the true
``ambient``. For an environment-lit scene (an ``envmap`` light) the comparable quantities are the environment's
mean radiance (its band 0) and its dominant direction (the direction of its luminance band 1), set against the
recovered ambient / SH band 0 plus the recovered direct lights' direction and irradiance.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
SETS = ("point_left", "sun_and_sky", "env_rotated")


def relight_dir(run: Path, scene: str, data: Path) -> Path:
    cfg = json.loads((run / "config.json").read_text())
    d = Path(cfg["data"]) / "relight"
    return d if (d / "relight.json").is_file() else data / "scenes" / scene / "relight"


def ensure_eval(run: Path, rdir: Path, force: bool, env_degree: int | None) -> dict:
    from triplet_cl.cli.main import main as cli_main

    m = json.loads((run / "metrics.json").read_text())
    if force or "relight" not in m or "soup" not in m["relight"]:
        args = ["eval", str(run), "--relight", str(rdir)]
        if env_degree is not None:
            args += ["--env-degree", str(env_degree)]
        if cli_main(args) != 0:
            raise SystemExit(f"triplet eval failed on {run}")
        m = json.loads((run / "metrics.json").read_text())
    return m


def rows_of(label: str, scene: str, run: Path, m: dict) -> list[str]:
    color = json.loads((run / "config.json").read_text())["train"].get("color", "encoded")
    out = []
    for stage in ("soup", "mesh"):
        r = m.get("relight", {}).get(stage)
        if r is None:
            continue
        nvs = m["psnr"] if stage == "soup" else m["mesh"]["psnr"]
        t = m.get("wall_time_s", 0) if stage == "soup" else m["mesh"].get("wall_time_s", 0)
        sets = " | ".join(f"{r['sets'][s]['psnr']:.2f}" if s in r["sets"] else "—" for s in SETS)
        a = r.get("albedo")
        alb = f"{a['psnr_raw']:.2f} / {a['psnr_scaled']:.2f}" if a else "—"
        out.append(f"| {scene} | {label} ({color}) | {stage} | {nvs:.2f} | {sets} | {alb} | {t:.0f} s |")
    return out


Y00 = 0.28209479177387814
LUM = np.array([0.2126, 0.7152, 0.0722])


def _angle(a, b) -> float:
    a, b = np.asarray(a, float), np.asarray(b, float)
    c = a @ b / max(np.linalg.norm(a) * np.linalg.norm(b), 1e-30)
    return float(np.degrees(np.arccos(np.clip(c, -1, 1))))


def _band1_dir(c: np.ndarray) -> np.ndarray:
    """Dominant direction of SH coefficients ``[3, >=4]`` (luminance band 1; ``kernels_cl/common/sh.h``:
    Y_1,-1 = -c y, Y_1,0 = c z, Y_1,1 = -c x)."""
    lum = LUM @ c[:, 1:4]
    return np.array([-lum[2], -lum[0], lum[1]])


def lights_vs_truth(run: Path, scene: str, data: Path, label: str = "") -> list[str]:
    """Rows comparing ``run/lights.json`` with ``scenes/<scene>/ground_truth.json`` (see the module docstring)."""
    from triplet_cl.lights import AmbientLight, DirectionalLight, PointLight, SHEnvironmentLight, lights_from_json
    from triplet_cl.relight import envmap_item_sh

    gt_file = data / "scenes" / scene / "ground_truth.json"
    if not gt_file.is_file():
        return [f"  {run}: no {gt_file}"]
    gt = json.loads(gt_file.read_text())
    rec = lights_from_json(json.loads((run / "lights.json").read_text()))
    pts = [lt for lt in rec if isinstance(lt, PointLight)]
    dirs = [lt for lt in rec if isinstance(lt, DirectionalLight)]
    amb = sum(float(lt.color.mean()) for lt in rec if isinstance(lt, AmbientLight))
    env = [lt for lt in rec if isinstance(lt, SHEnvironmentLight)]
    amb += sum(float(lt.coeffs[:, 0].mean() * Y00) for lt in env)
    out = []
    lab = label or run.parent.name
    rec_desc = "; ".join(
        [f"point at ({', '.join(f'{x:.2f}' for x in p.position)}) I {p.intensity.mean():.1f} "
         f"E(0) {p.intensity.mean() / max(p.position @ p.position, 1e-6):.2f}" for p in pts]
        + [f"directional to ({', '.join(f'{x:.2f}' for x in d.direction / np.linalg.norm(d.direction))}) "
           f"E {d.intensity.mean():.2f}" for d in dirs])
    for t in gt["lights"]:
        if t["type"] == "point":
            q, it = np.asarray(t["position"], float), float(np.mean(t["intensity"]))
            e_true = it / (q @ q)
            if pts:
                p = min(pts, key=lambda p: _angle(p.position, q))
                pi = float(p.intensity.mean())
                e_rec = pi / max(p.position @ p.position, 1e-6)
                out.append(f"| {scene} | {lab} | point | {np.linalg.norm(p.position - q):.2f} | "
                           f"{_angle(p.position, q):.1f} | {pi / it:.2f} | "
                           f"{e_rec / e_true:.2f} | {amb:.3f} / {gt.get('ambient', 0)} |")
            elif dirs:
                d = min(dirs, key=lambda d: _angle(d.direction, q))
                out.append(f"| {scene} | {lab} | point (as directional) | — | {_angle(d.direction, q):.1f} | — | "
                           f"{d.intensity.mean() / e_true:.2f} | {amb:.3f} / {gt.get('ambient', 0)} |")
        elif t["type"] == "envmap":
            c = envmap_item_sh(t, gt_file, "lights", 1)
            mean_true = float(c[:, 0].mean() * Y00)
            d_true = _band1_dir(c)
            direct = [(p.position, p.intensity.mean() / max(p.position @ p.position, 1e-6)) for p in pts] + \
                     [(d.direction, d.intensity.mean()) for d in dirs]
            ang = " / ".join(f"{_angle(v, d_true):.1f}" for v, _ in direct) or "—"
            e_dir = sum(e for _, e in direct)
            env_dir = " / ".join(f"{_angle(_band1_dir(e.coeffs), d_true):.1f}" for e in env
                                 if e.coeffs.shape[1] >= 4 and e.degree >= 1)
            out.append(f"| {scene} | {lab} | envmap | — | direct {ang}; SH band 1 {env_dir or '—'} | — | "
                       f"direct E(0) {e_dir:.2f} vs env πL̄ {np.pi * mean_true:.2f} | "
                       f"{amb:.3f} / {mean_true:.3f} (env mean) |")
    out.append(f"|  |  | recovered: {rec_desc} |  |  |  |  |  |")
    return out


def view_images(runs: dict, scene: str, data: Path, out: Path, view: int = 0) -> Path:
    """One test view: rows = light sets + albedo; columns = ground truth, then each run's mesh (else soup)."""
    from triplet_cl.datasets.images import read_image
    from triplet_cl.io import write_png
    from triplet_cl.relight import Relighter, load_light_sets
    from triplet_cl.train import Trainer

    rdir = None
    cols: list[list[np.ndarray]] = []
    for run in runs.values():
        rdir = relight_dir(run, scene, data)
        tr = Trainer(None, run, resume=True, quiet=True)
        rl = Relighter(tr)
        v = rl.views("test")[view]
        col = []
        for ls in load_light_sets(rdir / "relight.json"):
            img, _ = rl.render(rl.with_lights(ls.lights), v.camera, np.ones(3))
            col.append(np.clip(img, 0, 1))
        rgb, a = rl.render_albedo(v.camera)
        col.append(np.clip(rgb * a[..., None] + (1 - a[..., None]), 0, 1))
        cols.append(col)
    gt = []
    for ls in load_light_sets(rdir / "relight.json"):
        im = read_image(ls.images / f"{Path(v.name).name}.png")
        gt.append(im.rgb * im.alpha[..., None] + (1 - im.alpha[..., None]))
    alb = json.loads((rdir / "relight.json").read_text())["albedo"]
    im = read_image(rdir / alb / f"{Path(v.name).name}.png")
    gt.append(im.rgb * im.alpha[..., None] + (1 - im.alpha[..., None]))
    grid = np.concatenate([np.concatenate(c, 0) for c in [gt, *cols]], 1)
    path = out / f"relight_{scene}_view{view}.png"
    write_png(path, grid)
    return path


def gt_asset(scene_dir: Path, meshes: Path) -> tuple[np.ndarray, np.ndarray, np.ndarray, dict]:
    """A scene's ground-truth asset as our renderer takes it: ``(V, F, raw material [n, 6], ground_truth.json)``,
    ``gt_mesh.obj`` subdivided twice, the texture's base colour (linear) sampled at each vertex's UV (from the
    ``meshes`` folder), the truth's roughness and metallic, AO 1 (logit 30)."""
    import trimesh

    from triplet_cl.datasets.images import read_image
    from triplet_cl.ops.color import srgb_decode
    from triplet_cl.scene import logit

    gt = json.loads((scene_dir / "ground_truth.json").read_text())
    m = trimesh.load(scene_dir / "gt_mesh.obj", process=False)
    tex = next(meshes.glob(f"*/{gt['texture']}"))
    uv, V, F = np.asarray(m.visual.uv), np.asarray(m.vertices), np.asarray(m.faces)
    for _ in range(2):
        V, F, attr = trimesh.remesh.subdivide(V, F, vertex_attributes={"uv": uv})
        uv = attr["uv"]
    t = read_image(tex).rgb
    h, w = t.shape[:2]
    px = np.clip((uv[:, 0] % 1) * (w - 1), 0, w - 1).round().astype(int)
    py = np.clip((1 - uv[:, 1] % 1) * (h - 1), 0, h - 1).round().astype(int)
    n = len(V)
    mat = np.concatenate([logit(np.clip(srgb_decode(t[py, px]), 1e-4, 1 - 1e-4)),
                          np.full((n, 1), logit(gt["roughness"])), np.full((n, 1), logit(max(gt["metallic"], 1e-5))),
                          np.full((n, 1), 30.0)], 1)
    return V, F, mat, gt


def gt_ceiling(scene: str, degrees, renderers, data: Path, views: int = 4) -> None:
    from triplet_cl.datasets import load_dataset
    from triplet_cl.datasets.images import read_image
    from triplet_cl.relight import load_light_sets
    from triplet_cl.render import RenderSettings, render
    from triplet_cl.scene import Scene, logit
    from triplet_cl.train import psnr

    d = data / "scenes" / scene
    V, F, mat, gt = gt_asset(d, data / "meshes")
    n = len(V)
    test = load_dataset(str(d))["test"][:views]
    print(f"ground-truth mesh + material of {scene} ({n} vertices), {len(test)} test views, 2x2 supersampled:")
    print("| env SH degree | renderer | " + " | ".join(SETS) + " |\n|---|---|" + "---|" * len(SETS))
    for deg in degrees:
        sets = load_light_sets(d / "relight" / "relight.json", deg)
        for renderer in renderers:
            res = []
            for ls in sets:
                sc = Scene.from_arrays(V, F, material=mat, alpha=np.full((n, 1), 30.0), lights=ls.lights)
                vis = bounce = None
                if renderer in ("vertex_ao", "bounce"):  # the ambient occlusion traced (the material's AO is 1)
                    from triplet_cl.mesh.bake import vertex_normals
                    from triplet_cl.visibility import vertex_ambient_occlusion

                    ao = vertex_ambient_occlusion(sc, vertex_normals(V, F), directions=64, ray_eps=0.01)
                    sc.material.data[:, 5] = logit(np.clip(ao, 1e-4, 1 - 1e-4))
                if renderer in ("vertex", "vertex_ao", "bounce"):  # raster, the cached per-vertex shadows
                    from triplet_cl.visibility import vertex_visibility

                    vis = vertex_visibility(sc, ray_eps=0.01)
                if renderer == "bounce":  # ... and one traced interreflection bounce (visibility.vertex_bounce)
                    from triplet_cl.mesh.bake import vertex_normals
                    from triplet_cl.visibility import vertex_bounce

                    bounce = vertex_bounce(sc, vertex_normals(V, F), vis=vis, ray_eps=0.01)
                ps = []
                for v in test:
                    st = RenderSettings(K=4, sigma=None, normals="vertex", background=(1, 1, 1), transfer="srgb",
                                        renderer="raster" if renderer in ("vertex", "vertex_ao", "bounce")
                                        else renderer)
                    r = render(sc, v.camera.scaled(2), st, vis=vis, bounce=bounce)
                    img = r.image.reshape(v.camera.height, 2, v.camera.width, 2, 3).mean((1, 3))
                    im = read_image(ls.images / f"{Path(v.name).name}.png")
                    ps.append(psnr(img, im.rgb * im.alpha[..., None] + (1 - im.alpha[..., None])))
                res.append(float(np.mean(ps)))
            print(f"| {deg} | {renderer} | " + " | ".join(f"{x:.2f}" for x in res) + " |")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--runs", nargs="*", default=[], help="LABEL=FOLDER of runs named after their scenes")
    p.add_argument("--scenes", default="spot_small,spot,bob_env")
    p.add_argument("--data", default=str(DATA), help="the shared data folder (scenes/, envmaps/, meshes/)")
    p.add_argument("--force", action="store_true", help="re-run the relight evaluation of every run")
    p.add_argument("--env-degree", type=int, help="SH degree of the environment maps (default: triplet's)")
    p.add_argument("--images", help="write relight_<scene>_view0.png (ground truth | each run) into this folder")
    p.add_argument("--lights", action="store_true", help="also the recovered lights against ground_truth.json")
    p.add_argument("--gt-ceiling", help="relight the ground-truth mesh + material of this scene instead")
    p.add_argument("--env-degrees", default="8", help="with --gt-ceiling: comma-separated SH degrees")
    p.add_argument("--renderers", default="raster,hybrid", help="with --gt-ceiling: comma-separated renderers "
                   "(raster, hybrid, raytrace, or vertex: raster with the cached per-vertex shadows, vertex_ao: and "
                   "the AO traced from the mesh, bounce: and one traced interreflection bounce)")
    a = p.parse_args(argv)
    data = Path(a.data)
    if a.gt_ceiling:
        gt_ceiling(a.gt_ceiling, [int(x) for x in a.env_degrees.split(",")], a.renderers.split(","), data)
        return 0
    runs = {}
    for spec in a.runs:
        label, _, folder = spec.partition("=")
        if not folder:
            p.error(f"--runs expects LABEL=FOLDER, got {spec!r}")
        runs[label] = Path(folder)
    print("| scene | run | stage | NVS PSNR | " + " | ".join(SETS) + " | albedo raw / scaled | time |")
    print("|---|---|---|---|" + "---|" * len(SETS) + "---|---|")
    for scene in a.scenes.split(","):
        found = {}
        for label, folder in runs.items():
            run = folder / scene
            if not (run / "metrics.json").is_file():
                print(f"| {scene} | {label} | — | (no run at {run}) |", file=sys.stderr)
                continue
            m = ensure_eval(run, relight_dir(run, scene, data), a.force, a.env_degree)
            found[label] = run
            for row in rows_of(label, scene, run, m):
                print(row, flush=True)
        if a.lights and found:
            print("\n| scene | run | true light | position error | direction error (deg) | intensity ratio | "
                  "irradiance ratio at centre | ambient: recovered / true |\n|---|---|---|---|---|---|---|---|")
            for label, run in found.items():
                for row in lights_vs_truth(run, scene, data, label):
                    print(row)
            print()
        if a.images and found:
            print(f"  images: {view_images(found, scene, data, Path(a.images))}", file=sys.stderr)
    return 0


if __name__ == "__main__":
    sys.exit(main())
