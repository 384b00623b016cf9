"""The fragment adjoint pass (``fragment_bwd.cl``, the largest kernel of a soup step and of a mesh step) on the
launches of real training steps, with and without the vector channel chunks (issue 20).

A copy of RUN (a trained soup) is resumed and trained for ``--capture`` steps; every ``fragment_bwd`` launch of
those steps is recorded with its arguments, then replayed ``--reps`` times each as built by default (the attribute
channels eight, four and two at a time) and with ``SCALAR_CHANNELS`` (one at a time: the reference), alternated,
on fresh output buffers; per launch the minimum times and whether the outputs (partial sums of the entries with
fragments, the window's partial sums, the hit marks) are the same bits.

    python bench/fragment_bwd_step.py RUN [--capture 3] [--reps 10] [--out FILE]
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
import time
from pathlib import Path

import numpy as np

OUTPUTS = ("partial_attr", "partial_mom", "v_sigma_tile", "entry_hit", "v_bary_out")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("run", help="a trained run (copied first; the copy is resumed)")
    ap.add_argument("--capture", type=int, default=3, help="training steps whose launches are replayed")
    ap.add_argument("--reps", type=int, default=10)
    ap.add_argument("--out", default=None, help="also append the table to this file")
    args = ap.parse_args()

    import pyopencl.array as cla

    import triplet_cl.ops.fragment_bwd as fb
    from triplet_cl.train import Trainer

    captured = []
    launch = fb.launch

    def spy(device, prog, kern, *a, **kw):
        if kern == "fragment_bwd":
            captured.append((device, a, dict(kw)))
        return launch(device, prog, kern, *a, **kw)

    with tempfile.TemporaryDirectory() as tmp:
        run = Path(tmp) / Path(args.run).name
        shutil.copytree(args.run, run, ignore=shutil.ignore_patterns("renders"))
        tr = Trainer(None, run, resume=True, quiet=True)
        fb.launch = spy
        try:
            for _ in range(args.capture):
                tr.step()
        finally:
            fb.launch = launch
        tr.device.queue.finish()
        rows = [f"# bench/fragment_bwd_step.py {args.run} ({time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}): "
                f"{len(captured)} launches of {args.capture} steps at iteration {tr.it}, {args.reps} reps each",
                "| launch | C | fragments | tiles | vector chunks (default) ms | scalar channels ms | ratio "
                "| same bits |",
                "|---|---|---|---|---|---|---|---|"]
        for i, (dev, a, kw) in enumerate(captured):
            q = dev.queue

            def replay(scalar: bool, dev=dev, a=a, kw=kw, q=q):
                k = dict(kw, defines={**kw["defines"], "SCALAR_CHANNELS": scalar})
                for o in OUTPUTS:
                    if o in k:
                        k[o] = cla.empty_like(kw[o])
                t0 = time.perf_counter()
                launch(dev, "fragment_bwd", "fragment_bwd", *a, **k)
                q.finish()
                return time.perf_counter() - t0, k

            _, r0 = replay(False)
            _, r1 = replay(True)
            hit = r0["entry_hit"].get() > 0
            same = True
            for o in OUTPUTS:
                if o in r0:
                    x, y = r0[o].get(), r1[o].get()
                    if o in ("partial_attr", "partial_mom"):
                        x, y = x[hit], y[hit]
                    same &= bool(np.array_equal(x, y))
            t = {False: [], True: []}
            for _ in range(args.reps):
                for scalar in (False, True):
                    t[scalar].append(replay(scalar)[0])
            v, s = 1e3 * min(t[False]), 1e3 * min(t[True])
            rows.append(f"| {i} | {kw.get('C', 0)} | {kw['frag_face'].shape[0]} | {a[0][0]} | {v:.2f} | {s:.2f} | "
                        f"{s / v:.2f}× | {same} |")
            print(rows[-1], flush=True)
    print("\n".join(rows[:3]))
    if args.out:
        with open(args.out, "a") as fh:
            fh.write("\n".join(rows) + "\n\n")


if __name__ == "__main__":
    main()
