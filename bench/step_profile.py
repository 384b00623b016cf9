"""Where one training step spends its time: every kernel, and the host share of every op on the tape.

Usage::

    python bench/step_profile.py [SCENE] [--steps 15] [--warmup 3] [--downscale 1] [--top 30]

SCENE: a folder, or a name under ``/work/shared/data/scenes`` (default ``spot``). The training
configuration is ``bench/train_step.py``'s (``TrainConfig`` defaults at full resolution from step 0).
Every kernel launch (``Device.kernel``) is wrapped with ``queue.finish()`` before and after, so its
wall time is its own; every :class:`~triplet_cl.autodiff.Function` of ``render.py``, ``losses.py``
and ``ops/color.py``, ``Adam.step`` and ``DensityStats.add`` is timed the same way and its host
share is its time minus the kernels it launched. Serialising the queue costs a little overlap, so
the step is slower than ``train_step.py`` says; the split is what this is for. Per row: the
minimum over the measured steps (load only adds time) and the median.
"""

from __future__ import annotations

import argparse
import collections
import tempfile
import time
from pathlib import Path

import numpy as np

SCENES = Path("/work/shared/data/scenes")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("scene", nargs="?", default="spot", help="a folder or a name under " + str(SCENES))
    ap.add_argument("--steps", type=int, default=15, help="measured steps")
    ap.add_argument("--warmup", type=int, default=3, help="unmeasured steps first (kernel builds)")
    ap.add_argument("--downscale", type=int, default=1, help="dataset downscale factor")
    ap.add_argument("--top", type=int, default=30, help="rows per table")
    ap.add_argument("--mesh", default=None, metavar="RUN",
                    help="profile the mesh stage's refinement step on this trained run instead (SCENE unused): its "
                         "mesh extracted, --warmup steps, then --steps steps of a later round (no remesh, pixel "
                         "filter 0.5); per step, the mean over the steps")
    ap.add_argument("--resume", default=None, metavar="RUN",
                    help="profile the soup's step on this trained run's state (SCENE unused) instead of a fresh soup: "
                         "a late step has the grown, opaque soup that most of a run's time goes to")
    ap.add_argument("--checkpoint", default=None, metavar="NAME",
                    help="with --resume: the checkpoint to start from (e.g. ckpt_0002000.npz; default: the latest)")
    args = ap.parse_args()
    if args.resume is not None and args.mesh is not None:
        raise SystemExit("step_profile.py: error: give --resume RUN (the soup's step) or --mesh RUN (the mesh "
                         "stage's), not both")
    if args.checkpoint is not None and args.resume is None:
        raise SystemExit("step_profile.py: error: --checkpoint needs --resume RUN")
    scene = args.scene if Path(args.scene).is_dir() else str(SCENES / args.scene)
    if args.resume is None and args.mesh is None and not Path(scene).is_dir():
        raise SystemExit(f"step_profile.py: error: scene {args.scene!r} is neither a folder nor a name under {SCENES}")

    from triplet_cl.autodiff import Function

    from triplet_cl import density as density_mod
    from triplet_cl import device as device_mod
    from triplet_cl import losses, optim, render
    from triplet_cl import train as train_mod
    from triplet_cl.ops import color

    kern_t = collections.defaultdict(float)  # per kernel name, this step
    kern_n = collections.Counter()  # launches per kernel name, all measured steps
    total_k = [0.0]
    fetch = device_mod.Device.kernel

    class Timed:
        def __init__(self, k, name):
            self.k, self.name = k, name

        def __call__(self, queue, *a, **kw):
            queue.finish()
            t0 = time.perf_counter()
            ev = self.k(queue, *a, **kw)
            queue.finish()
            dt = time.perf_counter() - t0
            kern_t[self.name] += dt
            kern_n[self.name] += 1
            total_k[0] += dt
            return ev

        def __getattr__(self, a):
            return getattr(self.k, a)

    def timed_fetch(self, f, k, defines=None, real=np.float32):
        return Timed(fetch(self, f, k, defines, real), k)

    device_mod.Device.kernel = timed_fetch
    op_wall = collections.defaultdict(float)
    op_host = collections.defaultdict(float)
    dev = [None]

    def wrap(cls, meth):
        fn = getattr(cls, meth)

        def timed(self, *a, **kw):
            if dev[0] is not None:
                dev[0].queue.finish()
            k0, t0 = total_k[0], time.perf_counter()
            out = fn(self, *a, **kw)
            if dev[0] is not None:
                dev[0].queue.finish()
            dt = time.perf_counter() - t0
            op_wall[f"{cls.__name__}.{meth}"] += dt
            op_host[f"{cls.__name__}.{meth}"] += dt - (total_k[0] - k0)
            return out
        setattr(cls, meth, timed)

    seen = set()
    for mod in (render, losses, color):
        for c in vars(mod).values():
            if isinstance(c, type) and issubclass(c, Function) and c is not Function and c not in seen:
                seen.add(c)
                for m in ("forward", "backward"):
                    if m in c.__dict__:
                        wrap(c, m)
    wrap(optim.Adam, "step")
    wrap(density_mod.DensityStats, "add")

    if args.mesh:
        mesh_profile(args, dev, kern_t, kern_n, total_k, op_wall, op_host)
        return
    cfg = train_mod.TrainConfig(iterations=10**6, warmup_until=0, half_res_until=0, checkpoint_every=0,
                                downscale=args.downscale, seed=0)
    rows_k, rows_w, rows_h, steps, kernels = (collections.defaultdict(list), collections.defaultdict(list),
                                              collections.defaultdict(list), [], [])
    with tempfile.TemporaryDirectory(prefix="step_profile_") as run_dir:
        if args.resume is not None:
            tr = resumed_trainer(args, Path(run_dir) / "run")
        else:
            tr = train_mod.Trainer(scene, run_dir, cfg, quiet=True)
        dev[0] = tr.device
        for i in range(args.warmup + args.steps):
            kern_t.clear()
            op_wall.clear()
            op_host.clear()
            k0, t0 = total_k[0], time.perf_counter()
            tr.step()
            if i < args.warmup:
                kern_n.clear()
                continue
            steps.append(time.perf_counter() - t0)
            kernels.append(total_k[0] - k0)
            for k, v in kern_t.items():
                rows_k[k].append(v)
            for k in op_wall:
                rows_w[k].append(op_wall[k])
                rows_h[k].append(op_host[k])
        cam = tr.ds.train[0].camera
        name = f"--resume {Path(args.resume).name} at {tr.it}" if args.resume else Path(scene).name
        print(f"# bench/step_profile.py {name} {cam.width}x{cam.height}, {len(tr.scene.F)} faces, "
              f"{args.steps} steps, {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}")

    def ms(x):
        return 1e3 * float(x)

    print(f"step (serialised)  min {ms(min(steps)):8.2f}  median {ms(np.median(steps)):8.2f} ms")
    print(f"kernels            min {ms(min(kernels)):8.2f}  median {ms(np.median(kernels)):8.2f} ms")
    print(f"\n{'kernel':<28}{'min':>9}{'median':>9}{'launches':>10}")
    for k in sorted(rows_k, key=lambda k: -min(rows_k[k]))[:args.top]:
        print(f"{k:<28}{ms(min(rows_k[k])):>9.2f}{ms(np.median(rows_k[k])):>9.2f}{kern_n[k] / args.steps:>10.1f}")
    print(f"\n{'op':<32}{'wall min':>9}{'host min':>9}{'host med':>9}")
    for k in sorted(rows_h, key=lambda k: -min(rows_h[k]))[:args.top]:
        print(f"{k:<32}{ms(min(rows_w[k])):>9.2f}{ms(min(rows_h[k])):>9.2f}{ms(np.median(rows_h[k])):>9.2f}")


def copied_trainer(src, run: Path, option: str, checkpoint: str | None = None):
    """A trainer resumed from a copy of the trained run ``src`` (given as ``option``) in ``run``, at ``checkpoint``
    (default: its latest)."""
    import shutil

    from triplet_cl import train as train_mod

    src = Path(src)
    if not (src / "config.json").is_file():
        raise SystemExit(f"step_profile.py: error: {option} {src} is not a trained run (no config.json)")
    shutil.copytree(src, run, ignore=shutil.ignore_patterns("renders", "mesh*", "*.tmp"))
    if checkpoint is not None:
        if not (run / "checkpoints" / checkpoint).is_file():
            raise SystemExit(f"step_profile.py: error: --checkpoint {checkpoint} is not in {src}/checkpoints")
        (run / "checkpoints" / "latest").write_text(checkpoint)
    return train_mod.Trainer(None, run, resume=True, quiet=True)


def resumed_trainer(args, run: Path):
    """``--resume``: the trainer at ``--checkpoint``, with no checkpoint written while profiling."""
    from dataclasses import replace

    tr = copied_trainer(args.resume, run, "--resume", args.checkpoint)
    tr.cfg = replace(tr.cfg, iterations=10**6, checkpoint_every=0)
    return tr


def mesh_profile(args, dev, kern_t, kern_n, total_k, op_wall, op_host) -> None:
    """``--mesh RUN``: the same tables for the mesh stage's refinement step (means over ``--steps`` steps)."""
    from dataclasses import replace

    from triplet_cl.mesh import refine as refine_mod

    with tempfile.TemporaryDirectory(prefix="step_profile_mesh_") as d:
        tr = copied_trainer(args.mesh, Path(d) / "run", "--mesh")
        dev[0] = tr.device
        cfg = replace(refine_mod.MeshConfig(), iterations=max(args.warmup, 1), remesh_every=0, pixel_sigma=0.5)
        st = refine_mod.MeshStage(tr, cfg, quiet=True)
        scene = st.extract(tr.scene)
        st.refine(scene, 1)  # warm-up: kernel builds, caches
        for x in (kern_t, kern_n, op_wall, op_host):
            x.clear()
        k0 = total_k[0]
        st.cfg = replace(cfg, iterations=args.steps)
        st.history.clear()
        t0 = time.perf_counter()
        st.refine(scene, 1)
        wall = time.perf_counter() - t0
        cam = tr.ds.train[0].camera
        n = args.steps
        when = time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime())
        print(f"# bench/step_profile.py --mesh {Path(args.mesh).name}: {cam.width}x{cam.height} photos, supersample "
              f"{cfg.supersample}, {len(scene.F)} faces, {n} steps, {when}")
        print(f"step (serialised)  mean {1e3 * wall / n:8.2f} ms")
        print(f"kernels            mean {1e3 * (total_k[0] - k0) / n:8.2f} ms")
        print(f"\n{'kernel':<28}{'mean':>9}{'launches':>10}")
        for k in sorted(kern_t, key=lambda k: -kern_t[k])[:args.top]:
            print(f"{k:<28}{1e3 * kern_t[k] / n:>9.2f}{kern_n[k] / n:>10.1f}")
        print(f"\n{'op':<32}{'wall mean':>10}{'host mean':>10}")
        for k in sorted(op_host, key=lambda k: -op_host[k])[:args.top]:
            print(f"{k:<32}{1e3 * op_wall[k] / n:>10.2f}{1e3 * op_host[k] / n:>10.2f}")


if __name__ == "__main__":
    main()
