"""Cost of the training finiteness guard per iteration (issue 21).

The guard: (1) the gradient norm of each Adam group, already computed for clipping/logging, is tested
with ``math.isfinite`` (free); (2) every updated parameter array gets ``np.isfinite(x).all()`` after
the update (parameters live in host memory: numpy; the device gradients are read back by Adam
anyway); (3) the rendered image gets ``np.isfinite(image).all()`` before the loss. This times
(2) + (3) on the real arrays of a trainer and compares with the mean step time.

    .venv/bin/python bench/guard.py [--faces 20000 200000] [--steps 20]
"""

from __future__ import annotations

import argparse
import tempfile
import time
import timeit
from dataclasses import replace
from pathlib import Path

import numpy as np
from triplet_cl.cli.main import demo_data_path

from triplet_cl.train import TrainConfig, Trainer


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("--faces", type=int, nargs="+", default=[20_000, 200_000])
    ap.add_argument("--steps", type=int, default=20)
    ap.add_argument("--data", default=str(demo_data_path()))
    a = ap.parse_args()
    print(f"{'faces':>8} {'image':>9} {'step ms':>9} {'guard ms':>9} {'share':>7}")
    for n in a.faces:
        cfg = replace(TrainConfig(), init_points=n, warmup_until=0, half_res_until=0, checkpoint_every=0)
        cfg.density = replace(cfg.density, max_faces=max(n, 200_000), densify_from=10**9)
        with tempfile.TemporaryDirectory() as d:
            tr = Trainer(a.data, Path(d) / "r", cfg, quiet=True)
            tr.step()  # warm-up (kernel builds)
            t0 = time.perf_counter()
            for _ in range(a.steps):
                tr.step()
            step = (time.perf_counter() - t0) / a.steps
            v = tr.ds.train[0]
            img = np.zeros((v.camera.height, v.camera.width, 3), np.float32)
            params = [p.data for g in tr.opt.groups.values() for p in g.params]

            def guard(params=params, img=img):
                for x in params:
                    np.isfinite(x).all()
                np.isfinite(img).all()

            g = min(timeit.repeat(guard, number=20, repeat=5)) / 20
            print(f"{n:8d} {img.shape[1]:4d}x{img.shape[0]:<4d} {step * 1e3:9.1f} {g * 1e3:9.3f} {g / step:7.2%}")


if __name__ == "__main__":
    main()
