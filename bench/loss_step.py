"""Benchmark: the device photometric losses (value + adjoint) of one training step, this tree beside an older commit.

Usage::

    python bench/loss_step.py [--sizes 96,200,400] [--baseline COMMIT] [--steps 20] [--warmup 3] [--rounds 2]
                              [--out bench/results/NAME.txt] [--note "why"]

Per size S and tree, a fresh subprocess times on random float32 ``[S, S, 3]`` device images the two device losses a
training step uses: ``float32`` (``photometric_loss_and_grad`` on device arrays, ``losses.cl``: the soup above 96² and
the mesh stage) and ``exact`` (``photometric_loss_and_grad_exact``, ``ssim_exact.cl``, bit for bit the numpy loss: the
soup at 96² and below, e.g. the demo), each with its value on the host, as the trainer reads it. Minimum over the
``--steps`` calls after ``--warmup``, then the least loaded of ``--rounds`` alternating rounds. The baseline is
checked out into a temporary worktree and imported through ``bench/train_step.py``'s shim; default baseline: the
merge-base of ``HEAD`` and ``main``. The adjoints of both trees are compared bit for bit (``same``: the exact loss
must say yes).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import train_step as shared  # noqa: E402  (a sibling script: its worktree, worker, rounds and table helpers)

KINDS = ("float32", "exact")


def worker(args) -> None:
    tree = Path(args.tree).resolve()
    shared.import_tree(tree)
    import numpy as np
    import pyopencl.array as cla

    from triplet_cl import losses
    from triplet_cl.device import get_device

    assert Path(losses.__file__).resolve().is_relative_to(tree), losses.__file__
    s = int(args.size)
    dev = get_device()
    q = dev.queue
    rng = np.random.default_rng(0)
    xh, yh = (rng.random((s, s, 3)).astype(np.float32) for _ in range(2))
    x, y = cla.to_device(q, xh), cla.to_device(q, yh)

    def f32():
        value, v = losses.photometric_loss_and_grad(x, y)
        return float(value), v.get()

    def exact():
        loss, v = losses.photometric_loss_and_grad_exact(dev, x, xh, yh)
        return loss.value(), v.get()

    out = {}
    for name, fn in zip(KINDS, (f32, exact), strict=True):
        ts = []
        for i in range(args.warmup + args.steps):
            t0 = time.perf_counter()
            value, v = fn()
            if i >= args.warmup:
                ts.append(time.perf_counter() - t0)
        out[name] = 1e3 * min(ts)
        out[name + "_digest"] = hashlib.sha1(v.tobytes()).hexdigest()
    print("RESULT " + json.dumps(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--sizes", default="96,200,400", help="comma-separated image sizes S (S x S x 3)")
    args = shared.comparison_args(ap, worker, steps=20, warmup=3, hidden="--size")
    if args is None:
        return
    sizes = [int(v) for v in args.sizes.split(",") if v]
    if not sizes or min(sizes) < 1:
        raise SystemExit(f"loss_step.py: error: --sizes must be positive integers, got {args.sizes!r}")
    base_sha, head = shared.compared_commits(args.baseline)

    def run(tree, size):
        return shared.run_script_worker(__file__, tree, str(size), ["--size", str(size), "--steps", str(args.steps),
                                                             "--warmup", str(args.warmup)])

    def keep(r, prev):
        return {k: (min(r[k], prev[k]) if k in KINDS else r[k]) for k in r}

    lines = []
    with shared.worktree(base_sha) as wt:
        res = shared.alternate_rounds(sizes, args.rounds, wt, run, keep)
    lines.append(f"# bench/loss_step.py  {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}  old = {base_sha[:10]}  "
                 f"new = {head}  steps={args.steps} warmup={args.warmup} rounds={args.rounds}")
    if args.note:
        lines.append(f"# why: {args.note}")
    lines.append(f"{'size':>9}  {'loss':<8}{'old ms':>9}{'new ms':>9}{'o/n':>7}  same adjoint")
    for s in sizes:
        o, n = res[(s, "old")], res[(s, "new")]
        for k in KINDS:
            same = "yes" if o[k + "_digest"] == n[k + "_digest"] else "no"
            lines.append(f"{f'{s}x{s}':>9}  {k:<8}{o[k]:>9.2f}{n[k]:>9.2f}{o[k] / n[k]:>7.2f}  {same}")
    shared.write_table("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
