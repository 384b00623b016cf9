"""Decomposition ceiling (issue 18): what albedo / relight the *mesh stage's* optimisation reaches when the geometry
is the ground truth's, so that what is left is the light model's and the BRDF's share.

The ground-truth mesh (``gt_mesh.obj`` subdivided) is fitted to the training photos by the mesh stage's own loop
(``MeshStage.refine``) with the positions frozen; the materials start from the soup stage's initial values. The
lights are either the ground truth's frozen (``--lights gt``) or training's initial lights, learned (``--lights
learn``). Then ``evaluate_relight`` on the test views, as ``triplet eval --relight`` does for a mesh run.

This is a diagnostic: ``ground_truth.json`` and ``gt_mesh.obj`` are read to set up the check, never as a default.

    python bench/diag_ceiling.py DATA/scenes/spot_small --out /tmp/ceil --lights gt,learn
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def gt_mesh(data: Path, subdivide: int):
    """The ground-truth mesh subdivided, and its base colour per vertex (the texture's nearest texel, linear)."""
    import trimesh

    from triplet_cl.datasets.images import read_image
    from triplet_cl.ops.color import srgb_decode

    m = trimesh.load(data / "gt_mesh.obj", process=False)
    V, F, uv = np.asarray(m.vertices, np.float64), np.asarray(m.faces), np.asarray(m.visual.uv)
    for _ in range(subdivide):
        V, F, attr = trimesh.remesh.subdivide(V, F, vertex_attributes={"uv": uv})
        uv = attr["uv"]
    gt = json.loads((data / "ground_truth.json").read_text())
    t = read_image(next((data.parents[1] / "meshes").glob(f"*/{gt['texture']}"))).rgb
    h, w = t.shape[:2]
    px = np.clip((uv[:, 0] % 1) * (w - 1), 0, w - 1).round().astype(int)
    py = np.clip((1 - uv[:, 1] % 1) * (h - 1), 0, h - 1).round().astype(int)
    return V, F, srgb_decode(t[py, px])


def run(data: Path, out: Path, lights_mode: str, iterations: int, subdivide: int, fix: str, gtv: float | None = None,
        light_phase: int = 0) -> dict:
    from diag_lights import gt_lights

    from triplet_cl.mesh.refine import MeshConfig, MeshStage, save_mesh_state
    from triplet_cl.relight import Relighter, evaluate_relight
    from triplet_cl.scene import Scene, default_material_raw, logit
    from triplet_cl.train import TrainConfig, Trainer, tie_rows

    cfg = TrainConfig(iterations=1)
    tr = Trainer(str(data), out, cfg, quiet=True)
    # as after a soup's training: the mesh stage shades with the cached shadows only past shadow_from (a fresh
    # trainer is at iteration 0; until session 38 this diagnostic ran without cast shadows, and read that as the BRDF)
    tr.it = max(tr.it, tr.cfg.shadow_from)
    V, F, albedo = gt_mesh(data, subdivide)
    mat = default_material_raw(len(V), tr.scene.brdf).astype(np.float64)
    if "albedo" in fix:
        mat[:, :3] = logit(np.clip(albedo, 1e-4, 1 - 1e-4))
    if "metallic" in fix:
        mat[:, 4] = logit(1e-4)
    if "roughness" in fix:
        gt = json.loads((data / "ground_truth.json").read_text())
        mat[:, 3] = logit(gt["roughness"])
    if lights_mode == "gt":
        lights = gt_lights(data)
    elif lights_mode.startswith("run:"):  # the lights a trained run recovered (its lights.json)
        from triplet_cl.lights import lights_from_json

        lights = lights_from_json(json.loads((Path(lights_mode[4:]) / "lights.json").read_text())["lights"])
    else:
        lights = tr.scene.current_lights()
    if "ao" in fix:
        mat[:, 5] = 30.0
    scene = Scene.from_arrays(V, F, material=mat, alpha=np.full((len(V), 1), 30.0), lights=lights,
                              brdf=tr.scene.brdf, dtype=np.float32)
    mc = MeshConfig(iterations=iterations, lr_position=0.0, remesh_every=0,
                    lr_lights=0.0 if lights_mode == "gt" else MeshConfig.lr_lights,
                    gtv_weight=MeshConfig.gtv_weight if gtv is None else gtv)
    stage = MeshStage(tr, mc, quiet=True)
    # the frozen channels keep their value: zero their gradient before each step (Adam then never moves them);
    # a light phase (light_phase steps first) ties every material channel to one value (the mean gradient)
    frozen = [j for j, name in ((0, "albedo"), (1, "albedo"), (2, "albedo"), (3, "roughness"), (4, "metallic"),
                                (5, "ao")) if name in fix]
    orig = stage.build_optimizer
    state = {"tied": light_phase > 0}

    def build(sc):
        opt = orig(sc)
        step = opt.step

        def masked_step():
            g = np.asarray(sc.material.grad)
            if state["tied"]:
                tie_rows(sc.material)
            g[:, frozen] = 0
            step()

        opt.step = masked_step
        return opt

    stage.build_optimizer = build
    if light_phase:
        stage.cfg.iterations = light_phase
        scene = stage.refine(scene, 0)
        state["tied"] = False
        stage.cfg.iterations = iterations
    scene = stage.refine(scene, 0)
    save_mesh_state(out / "mesh_stage.npz", scene, mc)
    rel = Relighter(tr, stage="mesh")
    res = evaluate_relight(rel, data / "relight")
    act = 1 / (1 + np.exp(-np.asarray(scene.material.data, np.float64)))
    res["materials"] = {"roughness_mean": float(act[:, 3].mean()), "metallic_mean": float(act[:, 4].mean()),
                        "ao_mean": float(act[:, 5].mean())}
    res["lights"] = [lt.to_json() for lt in scene.current_lights()]
    res["train_psnr_last100"] = float(np.mean([h["psnr"] for h in stage.history[-100:]]))
    return res


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", type=Path)
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--lights", default="gt,learn", help="comma list: gt (frozen truth), learn (training's initial "
                   "lights, learned), run:RUN (the lights of a trained run, learned)")
    p.add_argument("--iterations", type=int, default=600)
    p.add_argument("--subdivide", type=int, default=1)
    p.add_argument("--light-phase", type=int, default=0, help="steps with the albedo tied to one value per channel "
                   "before the free fit")
    p.add_argument("--gtv", type=float, default=None, help="graph-TV weight of the materials (default: the stage's)")
    p.add_argument("--fix", default="",
                   help="comma list of channels held at the truth / 0: albedo, roughness, metallic, ao")
    a = p.parse_args(argv)
    print("| lights | fixed | train PSNR | point_left | sun_and_sky | env_rotated | albedo raw / scaled | "
          "rough / metal / ao |\n|---|---|---|---|---|---|---|---|")
    for mode in a.lights.split(","):
        out = a.out / f"{mode.split(':')[0]}_{a.fix.replace(',', '+') or 'none'}"
        r = run(a.data, out, mode, a.iterations, a.subdivide, a.fix, a.gtv, a.light_phase)
        s, al, m = r["sets"], r["albedo"], r["materials"]
        print(f"| {mode} | {a.fix or '-'} gtv {a.gtv} phase {a.light_phase} | {r['train_psnr_last100']:.2f} | "
              + " | ".join(f"{s[k]['psnr']:.2f}" for k in ("point_left", "sun_and_sky", "env_rotated"))
              + f" | {al['psnr_raw']:.2f} / {al['psnr_scaled']:.2f} | {m['roughness_mean']:.2f} / "
              f"{m['metallic_mean']:.2f} / {m['ao_mean']:.2f} |", flush=True)
        print(json.dumps(r["lights"]), file=sys.stderr)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
