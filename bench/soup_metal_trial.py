"""The mesh stage's metal-or-dielectric trial (``mesh.refine.metallic_trial``) run on a soup in training, as a dry run:
what each hypothesis's fit gives (loss over the trial's second half, the tied roughness it reaches) at an iteration
of the soup's light phase, per capture. Why (issue 18, bench/results/soup_metallic_pocl_2026-11-27.txt): a soup held
as a dielectric puts a metal's surface where its highlights are (Chamfer 0.026; held as a metal: 0.0093), and the
mesh stage's rule (lower loss, a metal rougher than 0.8 refused) refused the metal on the metal capture's soup.
This collects what a soup-stage rule would have to separate, on metals and dielectrics alike; it decides nothing.

    python bench/soup_metal_trial.py DATA [DATA ...] [--at 0.9] [--steps 200] [--iterations N] [--probe soup|mesh]

``--at``: the trial's iteration as a fraction of the light phase (``TrainConfig.material_tie_until``).
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np


def dry_trial(tr, steps: int) -> dict:
    """Both hypotheses fitted from the soup's state at ``tr.it`` (the scene put back as it was, metallic included)."""
    from triplet_cl.activations import sigmoid
    from triplet_cl.datasets.base import resolve_background
    from triplet_cl.lights import balanced_lights, relative_lr_scales
    from triplet_cl.materials import get_brdf
    from triplet_cl.mesh.refine import metallic_trial, photometric_backward
    from triplet_cl.render import RenderSettings, render
    from triplet_cl.train import schedule

    cfg, s = tr.cfg, tr.scene
    brdf = get_brdf(s.brdf)
    col, rough = brdf.column("metallic"), brdf.column("roughness")
    scale, K, deg = schedule(cfg, tr.it)
    rng = np.random.default_rng(cfg.seed + 17)
    views = rng.integers(0, len(tr.ds.train), steps)
    bgs = (rng.uniform(0, 1, (steps, 3)) if cfg.background == "random"
           else np.tile(np.asarray(resolve_background(cfg.background), np.float64), (steps, 1)))
    vis = tr.visibility(tr.it)

    def loss_and_backward(k: int) -> float:
        bg = np.asarray(bgs[k], np.float32)
        cam, target = tr.targets.get(int(views[k]), scale, bg)
        st = RenderSettings(K=K, sigma=cfg.sigma, background=tuple(float(x) for x in bg),
                            sh_degree=deg if s.vertex_sh is not None else None, renderer=cfg.renderer,
                            transfer=tr.transfer)
        return photometric_backward(render(s, cam, st, tr.device, vis=vis), target, cfg.ssim_lambda)

    def after_step(lights_before=None) -> None:  # (the soup's own rule then, without the irradiance hold)
        s.light_params.data[...] = balanced_lights(cfg.white_light, s.lights, s.light_params.data, tr.priors.center,
                                                   True)

    albedo = [brdf.column(f"albedo_{c}") for c in "rgb"]
    tied = [c for c in range(brdf.num_channels) if c not in albedo]
    m0 = np.array(s.material.data)
    scales = relative_lr_scales(s.lights) if s.light_params is not None and cfg.lr_lights_mode == "relative" else None
    t = time.perf_counter()
    out = metallic_trial(s, tied, col, loss_and_backward, steps, lr_material=cfg.lr_material, rough_col=rough,
                         betas=tuple(cfg.betas), lr_lights=cfg.lr_lights, light_scale=scales,
                         after_step=after_step if s.light_params is not None else None)
    s.material.data[...] = m0
    lo, hi = out["loss"]["0.01"], out["loss"]["0.99"]
    return {"it": tr.it, "loss_dielectric": lo, "loss_metal": hi, "metal_margin_pct": 100 * (lo - hi) / lo,
            "roughness_dielectric": float(sigmoid(out["tied"]["0.01"][tied.index(rough)])),
            "roughness_metal": float(sigmoid(out["tied"]["0.99"][tied.index(rough)])),
            "rule": out["metallic"], "refused": out["refused"], "seconds": time.perf_counter() - t}


def mesh_probe(tr) -> dict:
    """The mesh stage's own decision on a mesh extracted from the soup at ``tr.it``: extraction, the pixel filter, the
    light phase's tied channels at their means, then ``MeshStage.choose_metallic`` (its rule, roughness refusal
    included); the soup is not touched."""
    from triplet_cl.activations import sigmoid
    from triplet_cl.materials import get_brdf
    from triplet_cl.mesh.refine import MeshConfig, MeshStage, tied_channels

    t = time.perf_counter()
    stage = MeshStage(tr, MeshConfig(), quiet=True)
    mesh = stage.extract(tr.scene)
    if stage.cfg.pixel_sigma is None:
        stage.resolve_pixel_filter(mesh)
    brdf = get_brdf(mesh.brdf)
    held = stage.held_columns(mesh)
    tied = [k for k in tied_channels(mesh.brdf) if k not in tr.ambient_pairs[1] and k not in held]
    m = np.asarray(mesh.material.data)
    m[:, tied] = m[:, tied].mean(axis=0, keepdims=True)
    out = stage.choose_metallic(mesh, tied, brdf.column("metallic"))
    lo, hi = out["loss"]["0.01"], out["loss"]["0.99"]
    rough = brdf.column("roughness")
    return {"it": tr.it, "loss_dielectric": lo, "loss_metal": hi, "metal_margin_pct": 100 * (lo - hi) / lo,
            "roughness_dielectric": float(sigmoid(out["tied"]["0.01"][tied.index(rough)])),
            "roughness_metal": float(sigmoid(out["tied"]["0.99"][tied.index(rough)])),
            "rule": out["metallic"], "refused": out["refused"], "seconds": time.perf_counter() - t}


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", nargs="+", type=Path)
    p.add_argument("--at", type=float, default=0.9)
    p.add_argument("--steps", type=int, default=200)
    p.add_argument("--iterations", type=int, help="the run's length (default: the trainer's default)")
    p.add_argument("--probe", choices=("soup", "mesh"), default="soup",
                   help="the trial on the soup itself, or the mesh stage's on a mesh extracted from it")
    a = p.parse_args(argv)
    from triplet_cl.train import TrainConfig, Trainer

    print("| capture | iteration | loss dielectric | loss metal | metal's margin % | roughness dielectric / metal | "
          "rule's choice (refused) |\n|---|---|---|---|---|---|---|", flush=True)
    for d in a.data:
        cfg = TrainConfig() if a.iterations is None else TrainConfig().with_iterations(a.iterations)
        with tempfile.TemporaryDirectory() as tmp:
            tr = Trainer(str(d), Path(tmp) / "run", cfg, quiet=True)
            at = int(a.at * tr.cfg.material_tie_until)
            while tr.it < at:
                tr.step()
            r = dry_trial(tr, a.steps) if a.probe == "soup" else mesh_probe(tr)
            tr.close_log()
        print(f"| {d.name} | {r['it']} | {r['loss_dielectric']:.5f} | {r['loss_metal']:.5f} | "
              f"{r['metal_margin_pct']:+.2f} | {r['roughness_dielectric']:.2f} / {r['roughness_metal']:.2f} | "
              f"{r['rule']} ({r['refused']}) |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
