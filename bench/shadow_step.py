"""Benchmark: the cost of shadows in a training step, raster vs cached per-vertex visibility vs ray-traced.

Usage::

    python bench/shadow_step.py RUN [RUN ...] [--steps 10] [--warmup 2] [--rounds 2] [--out FILE]

Each RUN is a trained run (copied to a temporary folder first: nothing is written into it). Its last
checkpoint is loaded (a realistic soup: faces, alphas, the learned light) and ``Trainer.step()`` runs
at full resolution with density control switched off, interleaving the configurations round by round
(the machine is shared: interleaving spreads the load):

- ``raster``: no shadows (today's default);
- ``vertex``: ``--shadows vertex``: the step with the cached visibility interpolated and shaded (the
  trace itself excluded: it runs every ``shadow_every`` steps, timed apart as ``trace``);
- ``hybrid-shadows``: ``--renderer hybrid`` with shadows only (per-fragment shadow rays and their adjoint);
- ``hybrid``: ``--renderer hybrid`` as shipped (shadows and the reflection bounce).

Per configuration the median step time (ms) over the measured steps, the minimum over rounds; ``trace`` is
``vertex_visibility`` alone (median of 3 per round); ``vertex amortised`` = vertex + trace / shadow_every.
"""

from __future__ import annotations

import argparse
import shutil
import statistics
import sys
import tempfile
import time
from dataclasses import replace
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

CONFIGS = ("raster", "vertex", "hybrid-shadows", "hybrid")


def set_config(tr, name: str) -> None:
    tr.cfg.renderer = "raster" if name in ("raster", "vertex") else "hybrid"
    tr.cfg.shadows = "vertex" if name == "vertex" else "off"
    tr._hybrid_reflections = name == "hybrid"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--warmup", type=int, default=2)
    ap.add_argument("--rounds", type=int, default=2)
    ap.add_argument("--out")
    args = ap.parse_args()

    from triplet_cl import render as render_mod
    from triplet_cl.train import Trainer
    from triplet_cl.visibility import vertex_visibility

    orig_settings = render_mod.RenderSettings

    lines = []

    def emit(s=""):
        print(s, flush=True)
        lines.append(s)

    for run in args.runs:
        tmp = Path(tempfile.mkdtemp(prefix="shadow_step_"))
        try:
            shutil.copytree(run, tmp / "run")
            tr = Trainer(None, tmp / "run", resume=True, quiet=True)
            tr.cfg.density = replace(tr.cfg.density, densify_until=0, alpha_reset_interval=10**9)
            tr.cfg.shadow_from = 0
            tr.cfg.half_res_until = tr.cfg.warmup_until = 0
            # hybrid without the bounce: RenderSettings(reflections=False) through the trainer
            import triplet_cl.train as train_mod

            def settings_factory(*a, _tr=tr, **kw):
                st = orig_settings(*a, **kw)
                if st.renderer == "hybrid" and not getattr(_tr, "_hybrid_reflections", True):
                    st.reflections = False
                return st

            train_mod.RenderSettings = settings_factory
            res = {c: [] for c in CONFIGS}
            trace = []
            nv = None
            for _ in range(args.rounds):
                for c in CONFIGS:
                    set_config(tr, c)
                    tr.shadow_cache.invalidate()
                    times = []
                    for k in range(args.warmup + args.steps):
                        if c == "vertex":
                            tr.visibility(tr.it)  # the trace outside the timed step
                        t0 = time.perf_counter()
                        tr.step()
                        if k >= args.warmup:
                            times.append(time.perf_counter() - t0)
                    res[c].append(statistics.median(times) * 1e3)
                tt = []
                for _ in range(3):
                    t0 = time.perf_counter()
                    v = vertex_visibility(tr.scene, tr.device)
                    tt.append(time.perf_counter() - t0)
                nv = v.shape
                trace.append(statistics.median(tt) * 1e3)
            train_mod.RenderSettings = orig_settings
            best = {c: min(v) for c, v in res.items()}
            tmin = min(trace)
            every = tr.cfg.shadow_every
            emit(f"run {run}: {len(tr.scene.F)} faces, {nv[0]} vertices x {nv[1]} shadowed lights, "
                 f"{tr.ds.train[0].rgb.shape[1]}x{tr.ds.train[0].rgb.shape[0]} px, steps {args.steps}, "
                 f"rounds {args.rounds}")
            emit(f"{'config':<24}{'ms/step':>10}{'x raster':>10}")
            for c in CONFIGS:
                emit(f"{c:<24}{best[c]:>10.1f}{best[c] / best['raster']:>10.2f}")
            am = best["vertex"] + tmin / every
            emit(f"{'trace (vertex_visibility)':<24}{tmin:>10.1f}")
            emit(f"{'vertex amortised /' + str(every):<24}{am:>10.1f}{am / best['raster']:>10.2f}")
            emit("")
        finally:
            shutil.rmtree(tmp, ignore_errors=True)
    if args.out:
        Path(args.out).write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
