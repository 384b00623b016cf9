"""Decomposition diagnostic (issue 18, item 1): how much of the albedo / relight error is the light model's?

Trains a scene with its lights set to the ground truth of ``ground_truth.json`` (point lights and the constant
``ambient``; Mitsuba's units map one to one, see ``triplet_cl/relight.py``) and **frozen** (learning rate 0), all
else at the defaults; then ``triplet eval RUN --relight DATA/relight``. What is left of the error with the true
lights is geometry, shadows, inter-reflection and the BRDF's (roughness / metallic) share. Also prints the
roughness / metallic / ao the runs recovered (per-vertex, over the soup's faces with alpha > 0.5).

This is a diagnostic: ``ground_truth.json`` is read to set up the check, never as a training default.

    python bench/diag_lights.py DATA/scenes/spot_small --out /tmp/diag_gt --iterations 1500
    python bench/diag_lights.py DATA/scenes/spot_small --materials /tmp/final/demo2 /tmp/diag_gt   # no training
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

import numpy as np


def gt_lights(data: Path) -> list:
    """The ground truth's point lights and ambient as our lights (point + ambient in the training order)."""
    from triplet_cl.lights import AmbientLight, PointLight

    gt = json.loads((data / "ground_truth.json").read_text())
    out = []
    ambient = float(gt.get("ambient", 0.0))
    for it in gt["lights"]:
        if it["type"] == "constant":  # a constant environment is our ambient light
            ambient += float(np.mean(it["radiance"]))
            continue
        if it["type"] != "point":
            raise SystemExit(f"{data}: only point lights can be frozen by this diagnostic, got {it['type']}")
        out.append(PointLight(it["position"], np.broadcast_to(np.asarray(it["intensity"], float), 3).copy()))
    out.append(AmbientLight(np.full(3, ambient)))
    return out


def train_frozen(data: Path, out: Path, iterations: int, priors: str = "off") -> None:
    from triplet_cl.lights import pack_lights
    from triplet_cl.priors import LIGHT_WEIGHTS, MATERIAL_WEIGHTS
    from triplet_cl.train import TrainConfig, Trainer

    lights = gt_lights(data)
    weights = {"off": {}, "materials": MATERIAL_WEIGHTS,
               "metallic": {"prior_metallic": MATERIAL_WEIGHTS["prior_metallic"]},
               "all": {**MATERIAL_WEIGHTS, **LIGHT_WEIGHTS}}[priors]
    cfg = TrainConfig(iterations=iterations, lights=tuple(lt.KIND for lt in lights), lr_lights=0.0, **weights)
    tr = Trainer(str(data), out, cfg, quiet=True)
    tr.scene.lights = lights
    tr.scene.light_params.data[:] = pack_lights(lights).params.astype(tr.scene.light_params.data.dtype)
    m = tr.train()
    print(f"trained {out}: NVS {m['psnr']:.2f} dB, {m['faces']} faces, {m['wall_time_s']:.0f} s", file=sys.stderr)


def material_stats(run: Path) -> dict:
    """Alpha-weighted statistics of the soup's activated material channels (the last checkpoint)."""
    from triplet_cl.activations import sigmoid
    from triplet_cl.train import Trainer

    tr = Trainer(None, run, resume=True, quiet=True)
    s = tr.scene
    act = sigmoid(np.asarray(s.material.data, np.float64))
    alpha = sigmoid(np.asarray(s.alpha.data, np.float64)).reshape(-1)
    keep = alpha > 0.5
    names = ("roughness", "metallic", "ao") if s.brdf == "cook_torrance" else ()
    out = {"lights": [lt.to_json() for lt in s.current_lights()]}
    for j, n in zip((3, 4, 5), names, strict=False):
        v = act[keep, j]
        out[n] = {"mean": float(v.mean()), "p10": float(np.percentile(v, 10)), "median": float(np.median(v)),
                  "p90": float(np.percentile(v, 90)), "frac>0.9": float(np.mean(v > 0.9))}
    return out


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("data", help="a scene folder with ground_truth.json and relight/")
    p.add_argument("--out", help="run folder of the frozen-ground-truth-lights training")
    p.add_argument("--iterations", type=int, default=1500)
    p.add_argument("--priors", choices=("off", "materials", "metallic", "all"), default="off",
                   help="prior weights of the frozen run (priors.MATERIAL_WEIGHTS / LIGHT_WEIGHTS; default off)")
    p.add_argument("--materials", nargs="*", default=[], help="only print the material statistics of these runs")
    a = p.parse_args(argv)
    data = Path(a.data)
    if a.materials:
        for run in a.materials:
            print(run, json.dumps(material_stats(Path(run)), indent=None))
        return 0
    if not a.out:
        p.error("--out is needed to train")
    out = Path(a.out)
    if not (out / "metrics.json").is_file():
        train_frozen(data, out, a.iterations, a.priors)
    from triplet_cl.cli.main import main as cli_main

    m = json.loads((out / "metrics.json").read_text())
    if "relight" not in m:
        if cli_main(["eval", str(out), "--relight", str(data / "relight")]) != 0:
            return 1
        m = json.loads((out / "metrics.json").read_text())
    r = m["relight"]["soup"]
    sets = " | ".join(f"{k} {v['psnr']:.2f}" for k, v in r["sets"].items())
    print(f"{out}: NVS {m['psnr']:.2f} | {sets} | albedo raw/scaled {r['albedo']['psnr_raw']:.2f} / "
          f"{r['albedo']['psnr_scaled']:.2f}")
    print(json.dumps(material_stats(out)))
    return 0


if __name__ == "__main__":
    sys.exit(main())
