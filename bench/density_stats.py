"""Density-control diagnostics (issue 19): per densification step, the distribution of every statistic.

Trains with the defaults (or ``--no-error`` for the gradient criterion alone) and, at each
densification step, prints one JSON line: faces ``M``; faces visible in some view (``seen``) and
nearest in some pixel (``front``); percentiles (50, 90, 99, 99.9) of the mean screen-gradient
statistic (``mg_pct``, over visible views; ``fg_pct``, over views where the face is the nearest),
of the mean per-pixel error over a face's nearest pixels (``err_pct``), of the max projected bbox
area in pixels (``scr_px``), of the face alpha and of the longest edge / extent; how many faces
cross the gradient threshold either way, how many meet the alpha prune; then what the step did.

    python bench/density_stats.py /work/shared/data/scenes/gadget /tmp/density_diag --iterations 1300
"""

from __future__ import annotations

import argparse
import dataclasses
import json

import numpy as np

import triplet_cl.density as D
import triplet_cl.train as T


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("data")
    ap.add_argument("out")
    ap.add_argument("--iterations", type=int, default=1300)
    ap.add_argument("--no-error", action="store_true", help="gradient criterion only (error_threshold=None)")
    args = ap.parse_args()

    last: dict = {}
    render, loss = T.render, T.photometric_loss_and_grad

    def render_hook(*a, **k):
        last["r"] = r = render(*a, **k)
        return r

    def loss_hook(pred, target, **k):
        last["err"] = np.abs(np.asarray(pred) - np.asarray(target)).mean(axis=2)
        return loss(pred, target, **k)

    class Stats(D.DensityStats):
        def add(self, v_vs, visible, F, **kw):  # always collect the nearest-face and error statistics
            kw.pop("error", None), kw.pop("front", None)
            super().add(v_vs, visible, F, front=D.front_faces(last["r"].info["frags"]), error=last["err"], **kw)

    densify = T.densify_and_prune

    def densify_hook(scene, opt, stats, cfg, extent, **kw):
        def q(x):
            return [float(f"{v:.3g}") for v in np.percentile(x, [50, 90, 99, 99.9])] if x.size else []

        F, V = np.asarray(scene.F), np.asarray(scene.V.data)
        mg, fg, me = stats.mean_grad(), stats.mean_front_grad(), stats.mean_error()
        seen, front = stats.denom > 0, stats.front_views > 0
        af = D.face_alpha(scene.alpha.data, F)
        rec = dict(it=trainer.it, M=len(F), seen=int(seen.sum()), front=int(front.sum()),
                   mg_pct=q(mg[seen]), n_ge_thr=int((mg >= cfg.grad_threshold).sum()),
                   fg_pct=q(fg[front]), n_front_ge_thr=int((fg >= cfg.grad_threshold).sum()),
                   err_pct=q(me[front]), scr_px=q(stats.max_screen_area[front]), alpha_pct=q(af),
                   n_alpha_le=int((af <= cfg.prune_alpha).sum()),
                   edge_pct=q(D.face_longest_edges(V, F) / extent))
        rep = densify(scene, opt, stats, cfg, extent, **kw)
        rec.update(dataclasses.asdict(rep))
        print(json.dumps(rec), flush=True)
        return rep

    T.render, T.photometric_loss_and_grad, T.DensityStats, T.densify_and_prune = (
        render_hook, loss_hook, Stats, densify_hook)
    cfg = T.TrainConfig(iterations=args.iterations)
    if args.no_error:
        cfg.density = dataclasses.replace(cfg.density, error_threshold=None)
    trainer = T.Trainer(args.data, args.out, cfg, quiet=True)
    m = trainer.train()
    print(json.dumps({k: m.get(k) for k in ("psnr", "faces", "wall_time_s")}))


if __name__ == "__main__":
    main()
