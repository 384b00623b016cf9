"""Roughness / metallic recovery on small synthetic scenes rendered by our own renderer (issue 18, item 3).

A sphere soup (icosphere, one triangle = one triplet, per-vertex materials) is rendered from 8 views with a known
material and known lights; the materials are then fitted from training's initial values
(``materials.BRDF.initial_raw``: albedo 0.5, roughness 0.5 (0.9 before), metallic 0.1, AO 0.99) with training's loss
(L1 + SSIM), optimiser (Adam, betas (0.5, 0.999)) and material learning rate, the lights either frozen at the truth
(``--lights known``: the BRDF parameters alone) or learned from training's initial lights (``--lights learn``).
Prints the trajectory of the mean roughness / metallic / albedo over the vertices that see the light, and the
fit's RMSE, so that which parameter goes wrong, and when, can be read off.

Cases (``--case``):
  dielectric  orange albedo (0.6, 0.4, 0.25), roughness 0.3, metallic 0; a point light + ambient 0.03
  gold        gold albedo (1.0, 0.78, 0.34), roughness 0.35, metallic 1; a point light + ambient 0.05
  gold_env    the gold sphere under an SH environment (degree 4: a sky gradient and a soft sun blob)
  rough       the orange dielectric with roughness 0.8 (a rough surface must stay rough)

    python bench/diag_brdf.py --case gold --lights known --iterations 600
    python bench/diag_brdf.py --case dielectric --set init_roughness=0.5
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

CASES = {
    "dielectric": dict(albedo=(0.6, 0.4, 0.25), roughness=0.3, metallic=0.0, env=False, ambient=0.03),
    "gold": dict(albedo=(1.0, 0.78, 0.34), roughness=0.35, metallic=1.0, env=False, ambient=0.05),
    "gold_env": dict(albedo=(1.0, 0.78, 0.34), roughness=0.35, metallic=1.0, env=True, ambient=0.0),
    "rough": dict(albedo=(0.6, 0.4, 0.25), roughness=0.8, metallic=0.0, env=False, ambient=0.03),
}
LIGHT_POS = np.array([1.2, 2.0, 1.5])
LIGHT_I = 6.0


def sphere_soup(subdivisions: int = 3, radius: float = 0.8):
    import trimesh

    m = trimesh.creation.icosphere(subdivisions=subdivisions, radius=radius)
    V = np.asarray(m.vertices)[np.asarray(m.faces)].reshape(-1, 3)
    return V, np.arange(len(V)).reshape(-1, 3)


def cameras(res: int, n: int = 8):
    from triplet_cl.camera import Camera

    cams = []
    for k in range(n):
        t = 2 * np.pi * k / n
        eye = [3.0 * np.sin(t), 1.0 + 0.8 * np.cos(3 * t), 3.0 * np.cos(t)]
        cams.append(Camera.look_at(eye, [0, 0, 0], [0, 1, 0], 45, res, res))
    return cams


def sh_environment(degree: int = 4):
    """An SH environment (radiance >= 0.05 everywhere): a sky gradient and a soft sun blob towards +x+y+z."""
    from triplet_cl.lights import SHEnvironmentLight
    from triplet_cl.mesh.envmap import sh_basis

    n = 200
    th = (np.arange(n) + 0.5) / n * np.pi
    ph = (np.arange(2 * n) + 0.5) / (2 * n) * 2 * np.pi
    T, P = np.meshgrid(th, ph, indexing="ij")
    d = np.stack([np.sin(T) * np.cos(P), np.cos(T), np.sin(T) * np.sin(P)], -1)
    sun = np.array([0.5, 0.7, 0.5]) / np.linalg.norm([0.5, 0.7, 0.5])
    rad = 0.25 + 0.15 * d[..., 1] + 2.5 * np.maximum(d @ sun, 0) ** 6
    w = np.sin(T) * (np.pi / n) * (np.pi / n)
    Y = sh_basis(degree, d)
    c = np.einsum("ijk,ij->k", Y, rad * w)
    check = Y @ c
    assert check.min() > 0.02, check.min()
    return SHEnvironmentLight(np.tile(c, (3, 1)), degree)


def true_lights(case: dict):
    from triplet_cl.lights import AmbientLight, PointLight

    if case["env"]:
        return [sh_environment()]
    return [PointLight(LIGHT_POS, np.full(3, LIGHT_I)), AmbientLight(np.full(3, case["ambient"]))]


def make_scene(V, F, albedo, rough, metal, lights, ao=0.99):
    from triplet_cl.scene import Scene, logit

    act = np.tile(np.r_[albedo, rough, metal, ao], (len(V), 1))
    return Scene.from_arrays(V, F, material=logit(np.clip(act, 1e-4, 1 - 1e-4)),
                             alpha=np.full((len(V), 1), logit(0.999)), lights=lights)


def run(args) -> dict:
    from triplet_cl.lights import LightInit, initial_lights
    from triplet_cl.losses import photometric_loss_and_grad
    from triplet_cl.materials import get_brdf, highlight_vertices
    from triplet_cl.optim import Adam, ExponentialDecay
    from triplet_cl.priors import Priors
    from triplet_cl.render import RenderSettings, render
    from triplet_cl.train import TrainConfig

    case = CASES[args.case]
    settings = RenderSettings(K=8, sigma=None, background=(0.0, 0.0, 0.0))
    V, F = sphere_soup(args.subdivisions)
    cams = cameras(args.res, args.views)
    truth = make_scene(V, F, case["albedo"], case["roughness"], case["metallic"], true_lights(case))
    targets = [render(truth, c, settings).image.copy() for c in cams]

    kv = dict(kv.split("=") for kv in args.set)
    brdf = get_brdf("cook_torrance")
    ini = {c.name: c.init for c in brdf.channels}
    r0 = float(kv.pop("init_roughness", ini["roughness"]))
    m0 = float(kv.pop("init_metallic", ini["metallic"]))
    a0 = kv.pop("init_albedo", None)
    a0 = [ini["albedo_r"]] * 3 if a0 is None else (case["albedo"] if a0 == "truth" else [float(a0)] * 3)
    lr = float(kv.pop("lr_material", 0.05))
    lr_rm = float(kv.pop("lr_rm", lr))
    lr_final = float(kv.pop("lr_final", lr))  # exponential decay to this over the run (default: constant)
    if args.lights == "known":
        lights = true_lights(case)
    else:
        kinds = ["env"] if case["env"] else ["point", "ambient"]
        lights = initial_lights(kinds, LightInit(np.zeros(3), 3.0, np.array([0.0, 1.0, 0.0]), 4,
                                                 np.random.default_rng(0)))
    scene = make_scene(V, F, a0, r0, m0, lights, ini["ao"])
    opt = Adam()
    scale = np.ones((1, brdf.num_channels))
    scale[0, 3:5] = lr_rm / lr
    for j, name in enumerate(brdf.channel_names):  # scale_<channel>=0 freezes a channel
        scale[0, j] *= float(kv.pop(f"scale_{name}", 1.0))
    cfg_kw = {k: float(v) for k, v in kv.items()}
    cfg = TrainConfig(prior_from=0, **cfg_kw)
    priors = Priors(cfg, np.zeros(3))
    if (scale == 1).all():
        lr_rm = lr
    else:
        lr_rm = None
    sched = ExponentialDecay(lr, lr_final, args.iterations) if lr_final != lr else lr
    opt.add_group("material", [scene.material], lr=sched, lr_scale=[scale] if lr_rm is None else None,
                  betas=(0.5, 0.999))
    if args.lights == "learn" and scene.light_params is not None:
        opt.add_group("light_params", [scene.light_params], lr=args.lr_lights, betas=(0.5, 0.999))

    n = V / np.linalg.norm(V, axis=1, keepdims=True)
    if case["env"]:
        seen = np.ones(len(V), bool)
    else:
        to_l = LIGHT_POS - V
        seen = np.sum(n * to_l, axis=1) / np.linalg.norm(to_l, axis=1) > 0.2
    # vertices in (or near) a highlight in at least one view: the mirror direction of some camera is near the light
    hl = np.zeros(len(V), bool) if case["env"] else highlight_vertices(V, n, LIGHT_POS, cams)

    rng = np.random.default_rng(0)
    t0 = time.perf_counter()
    rows = []

    def report(it):
        act = brdf.activate(np.asarray(scene.material.data, np.float64))
        row = dict(it=it, rough=act[seen, 3].mean(), rough_hl=act[hl, 3].mean() if hl.any() else np.nan,
                   metal=act[seen, 4].mean(), metal_hl=act[hl, 4].mean() if hl.any() else np.nan,
                   alb=act[seen, :3].mean(axis=0))
        rows.append(row)
        if not args.quiet:
            print(f"it {it:5d} rough {row['rough']:.3f} (highlit {row['rough_hl']:.3f}) metal {row['metal']:.3f} "
                  f"albedo {np.round(row['alb'], 3)}", flush=True)

    for it in range(args.iterations):
        if it % args.every == 0:
            report(it)
        i = int(rng.integers(len(cams)))
        r = render(scene, cams[i], settings)
        r.backward(photometric_loss_and_grad(r.image, targets[i], lam=0.2)[1])
        priors.apply(scene, it)
        opt.step()
        opt.zero_grad()
        priors.project(scene)
    report(args.iterations)
    imgs = [render(scene, c, settings).image for c in cams]
    rmse = float(np.sqrt(np.mean((np.concatenate([x.reshape(-1, 3) for x in imgs])
                                  - np.concatenate([t.reshape(-1, 3) for t in targets])) ** 2)))
    out = dict(rows[-1], rmse=rmse, seconds=time.perf_counter() - t0, n_seen=int(seen.sum()), n_hl=int(hl.sum()))
    print(f"RESULT case={args.case} views={args.views} lights={args.lights} set={args.set} truth rough "
          f"{case['roughness']} metal {case['metallic']}: "
          f"rough {out['rough']:.3f} (highlit {out['rough_hl']:.3f}, {out['n_hl']} vertices) "
          f"metal {out['metal']:.3f} (highlit {out['metal_hl']:.3f}) albedo {np.round(out['alb'], 3)} "
          f"RMSE {rmse:.4f} ({out['seconds']:.0f} s)",
          flush=True)
    return out


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--case", choices=sorted(CASES), default="gold")
    p.add_argument("--lights", choices=("known", "learn"), default="known")
    p.add_argument("--iterations", type=int, default=600)
    p.add_argument("--every", type=int, default=100)
    p.add_argument("--res", type=int, default=48)
    p.add_argument("--views", type=int, default=8)
    p.add_argument("--subdivisions", type=int, default=3)
    p.add_argument("--lr-lights", type=float, default=0.02)
    p.add_argument("--set", nargs="*", default=[], help="KEY=VALUE: init_roughness, init_metallic, lr_material, "
                   "init_albedo (a value or truth), lr_final (decay), lr_rm (roughness / metallic columns' rate), "
                   "scale_<channel> (0 freezes it) or any TrainConfig prior_* field")
    p.add_argument("--quiet", action="store_true")
    run(p.parse_args(argv))


if __name__ == "__main__":
    main()
