"""One training run of a dev scene with material-setting overrides, then ``triplet eval --relight`` (issue 18, the
roughness / metallic measurements of README "Roughness and metallic").

``--init-roughness`` / ``--init-metallic`` set the Cook-Torrance descriptor's initial values for this process (an
A/B of the default without editing ``materials.py``); ``--set KEY=VALUE`` any TrainConfig field (floats).
The demo (``spot_small``) runs 1500 iterations as ``triplet train --demo`` does, the others the default 3000.
Prints one table row: NVS PSNR | relight per set | albedo raw / scaled | mean roughness / metallic | wall time.

    python bench/brdf_run.py spot_small --out /tmp/metals/demo_a --init-roughness 0.5 --set lr_lobe_scale=3
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
DATA = Path("/work/shared/data/scenes")
SETS = ("point_left", "sun_and_sky", "env_rotated")


def main(argv=None) -> int:
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("scene")
    p.add_argument("--out", type=Path, required=True)
    p.add_argument("--data", type=Path, default=DATA)
    p.add_argument("--init-roughness", type=float)
    p.add_argument("--init-metallic", type=float)
    p.add_argument("--set", nargs="*", default=[])
    p.add_argument("--label", default="")
    a = p.parse_args(argv)

    from triplet_cl import materials
    from triplet_cl.train import TrainConfig, Trainer

    ct = materials.COOK_TORRANCE
    ch = list(ct.channels)
    for name, v in (("roughness", a.init_roughness), ("metallic", a.init_metallic)):
        if v is not None:
            j = ct.channel_names.index(name)
            ch[j] = dataclasses.replace(ch[j], init=v)
    patched = dataclasses.replace(ct, channels=tuple(ch))
    materials.BRDFS[ct.name] = patched
    materials.COOK_TORRANCE = patched

    kv = dict(s.split("=", 1) for s in a.set)
    cfg = TrainConfig(**{k: float(v) for k, v in kv.items()})
    if a.scene == "spot_small":
        cfg = cfg.with_iterations(1500)
    data = a.data / a.scene
    t0 = time.time()
    tr = Trainer(str(data), a.out, cfg, quiet=True)
    m = tr.train()
    wall = time.time() - t0
    subprocess.run([sys.executable, "-m", "cli.main", "eval", str(a.out), "--relight", str(data / "relight")],
                   check=True, capture_output=True, cwd=Path(__file__).resolve().parents[1])
    mm = json.loads((a.out / "metrics.json").read_text())
    rl = mm["relight"]["soup"]
    act = patched.activate(np.asarray(tr.scene.material.data, np.float64))
    row = (f"| {a.scene} | {a.label} | {m['psnr']:.2f} | " + " | ".join(f"{rl['sets'][s]['psnr']:.2f}" for s in SETS)
           + f" | {rl['albedo']['psnr_raw']:.2f} / {rl['albedo']['psnr_scaled']:.2f} | {act[:, 3].mean():.2f} / "
           f"{act[:, 4].mean():.2f} | {len(tr.scene.F)} | {wall:.0f} s |")
    print("ROW " + row, flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
