"""Benchmark: the per-phase split of one training step, this tree beside an older commit.

Usage::

    python bench/train_step.py [--scenes spot,gadget] [--baseline COMMIT] [--steps 20] [--warmup 3]
                               [--rounds 2] [--downscale 1] [--out bench/results/NAME.txt]

For every scene (a folder, or a name under ``/work/shared/data/scenes``) the same training
configuration (``TrainConfig`` defaults at full resolution from step 0: K = faces_per_pixel, no
warm-up, no half-resolution phase, no densify/prune event inside the measured steps, density
statistics accumulated every step) runs ``--warmup`` + ``--steps`` iterations of
``Trainer.step()`` in a fresh subprocess per tree, alternating baseline and this tree ``--rounds``
times (the machine is shared: alternating spreads the load over both). Phases, in milliseconds
(median over the measured steps; per phase the minimum of that over the rounds, since load only adds
time — so ``total`` may exceed the sum of the phases' minima):

- ``render``, ``loss``, ``backward``: the trainer's own timers (``rec["render"]`` ...);
- ``stats``: density statistics (``DensityStats.add`` and the visible-face pass, timed by wrapping);
- ``adam``: the optimizer step and ``zero_grad`` (the trainer's ``step`` timer minus ``stats``);
- ``density``: the trainer's ``density`` timer (densify / prune / alpha reset; ~0 here);
- ``total``: the wall time of ``Trainer.step()``.

OpenCL queues are asynchronous, so a kernel enqueued in one phase may be paid in the next one that
waits; ``total`` is exact. The baseline is checked out with ``git worktree add --detach`` into a
temporary folder (removed afterwards) and imported through a small shim: the package maps
``autodiff/``, ``cli/``, ``kernels_cl/`` into ``triplet_cl.*`` (pyproject's package-dir), so the
worker builds the ``triplet_cl`` package object by hand with ``__path__ = [tree/triplet_cl, tree]``;
this tree is imported the same way, so both sides load alike. Default baseline: the merge-base of
``HEAD`` and ``main`` (the code this branch started from).
"""

from __future__ import annotations

import argparse
import contextlib
import importlib.util
import json
import os
import subprocess
import sys
import tempfile
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
SCENES = Path("/work/shared/data/scenes")
PHASES = ("render", "loss", "backward", "stats", "adam", "density", "total")


# ------------------------------------------------------------------------------------------------ worker


def import_tree(tree: Path):
    """Import ``triplet_cl`` from the source tree ``tree`` (not from site-packages)."""
    for name in [m for m in sys.modules if m == "triplet_cl" or m.startswith("triplet_cl.")]:
        del sys.modules[name]
    spec = importlib.util.spec_from_file_location(
        "triplet_cl", tree / "triplet_cl" / "__init__.py",
        submodule_search_locations=[str(tree / "triplet_cl"), str(tree)])
    mod = importlib.util.module_from_spec(spec)
    sys.modules["triplet_cl"] = mod
    spec.loader.exec_module(mod)
    return mod


def worker(args) -> None:
    tree = Path(args.tree).resolve()
    import_tree(tree)
    import numpy as np

    from triplet_cl import density as density_mod
    from triplet_cl import train as train_mod

    assert Path(train_mod.__file__).resolve().is_relative_to(tree), train_mod.__file__
    acc = {"stats": 0.0}

    def timed(fn):
        def wrapper(*a, **kw):
            t0 = time.perf_counter()
            try:
                return fn(*a, **kw)
            finally:
                acc["stats"] += time.perf_counter() - t0
        return wrapper

    density_mod.DensityStats.add = timed(density_mod.DensityStats.add)
    for name in ("visible_faces", "visible_face_mask"):  # whichever the tree's train.py calls
        if hasattr(train_mod, name):
            setattr(train_mod, name, timed(getattr(train_mod, name)))

    cfg = train_mod.TrainConfig(iterations=10**6, warmup_until=0, half_res_until=0, checkpoint_every=0,
                                downscale=args.downscale, seed=0)
    with tempfile.TemporaryDirectory(prefix="train_step_") as run_dir:
        tr = train_mod.Trainer(args.scene, run_dir, cfg, quiet=True)
        rows = []
        for i in range(args.warmup + args.steps):
            acc["stats"] = 0.0
            t0 = time.perf_counter()
            rec = tr.step()
            total = time.perf_counter() - t0
            if i < args.warmup:
                continue
            rows.append({"render": rec["render"], "loss": rec["loss_t"], "backward": rec["backward"],
                         "stats": acc["stats"], "adam": rec["step"] - acc["stats"], "density": rec["density"],
                         "total": total, "psnr": rec["psnr"]})
        cam = tr.ds.train[0].camera
        out = {k: 1e3 * float(np.median([r[k] for r in rows])) for k in PHASES}
        out.update(faces=len(tr.scene.F), size=f"{cam.width}x{cam.height}", K=cfg.faces_per_pixel,
                   psnr_last=float(rows[-1]["psnr"]))
    print("RESULT " + json.dumps(out))


# ------------------------------------------------------------------------------------------------ driver


def git(*a, cwd=ROOT) -> str:
    return subprocess.run(["git", *a], cwd=cwd, check=True, capture_output=True, text=True).stdout.strip()


@contextlib.contextmanager
def worktree(commit_sha: str):
    """``commit_sha`` checked out (detached) into a temporary ``git worktree``, removed afterwards."""
    tmp = Path(tempfile.mkdtemp(prefix="triplet_base_"))
    wt = tmp / "tree"
    git("worktree", "add", "--detach", str(wt), commit_sha)
    try:
        yield wt
    finally:
        git("worktree", "remove", "--force", str(wt))
        try:
            tmp.rmdir()
        except OSError:
            pass


def write_table(text: str, out: str | None) -> None:
    """Print ``text``; with ``out``, also write it there (a temporary file renamed into place)."""
    print(text)
    if out:
        path = Path(out)
        path.parent.mkdir(parents=True, exist_ok=True)
        tmp_out = path.with_suffix(path.suffix + ".tmp")
        tmp_out.write_text(text + "\n")
        tmp_out.replace(path)


def compared_commits(baseline: str | None) -> tuple[str, str]:
    """``(the baseline's full sha, this tree's short sha, "+dirty" when it has uncommitted changes)``."""
    base = baseline or default_baseline()
    base_sha = git("rev-parse", "--verify", base + "^{commit}")
    head = git("rev-parse", "--short", "HEAD") + ("+dirty" if git("status", "--porcelain", "--untracked-files=no")
                                                  else "")
    return base_sha, head


def default_baseline() -> str:
    try:
        return git("merge-base", "HEAD", "main")
    except subprocess.CalledProcessError:
        return git("rev-parse", "HEAD~1")


def alternate_rounds(inputs, rounds: int, base_tree: Path, run, keep) -> dict:
    """``{(input, "old" | "new"): result}``: ``rounds`` alternating calls of ``run(tree, input)`` on the baseline's
    tree and this one per input, a later round's result merged into the earlier by ``keep(result, previous)``."""
    res = {}
    for x in inputs:
        for _ in range(rounds):
            for label, tree in (("old", base_tree), ("new", ROOT)):
                r = run(tree, x)
                prev = res.get((x, label))
                res[(x, label)] = r if prev is None else keep(r, prev)
    return res


def run_script_worker(script: str, tree: Path, what: str, extra: list[str]) -> dict:
    """Run ``script --worker --tree TREE EXTRA...`` in a fresh process; its ``RESULT {json}`` line."""
    cmd = [sys.executable, str(Path(script).resolve()), "--worker", "--tree", str(tree), *extra]
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tempfile.gettempdir())
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"worker failed on {tree} / {what} (exit {p.returncode}):\n{p.stderr[-3000:]}")


def run_worker(tree: Path, scene: str, args) -> dict:
    return run_script_worker(__file__, tree, scene, ["--scene", scene, "--steps", str(args.steps), "--warmup",
                                                     str(args.warmup), "--downscale", str(args.downscale)])


def resolve_scene(s: str) -> str:
    p = Path(s)
    if p.is_dir():
        return str(p.resolve())
    if (SCENES / s).is_dir():
        return str(SCENES / s)
    raise SystemExit(f"train_step.py: error: scene {s!r} is neither a folder nor a name under {SCENES}")


def comparison_args(ap: argparse.ArgumentParser, worker, steps: int, warmup: int, hidden: str):
    """Parse the command line with the options of every old-beside-new benchmark (:func:`add_comparison_args`) and
    the worker's hidden input option ``hidden``; in worker mode run ``worker(args)`` and return None."""
    add_comparison_args(ap, steps=steps, warmup=warmup)
    ap.add_argument(hidden, help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args)
        return None
    return args


def add_comparison_args(ap: argparse.ArgumentParser, steps: int, warmup: int) -> None:
    """The options every old-beside-new benchmark takes (this script's and ``mesh_step.py``'s), worker mode included."""
    ap.add_argument("--baseline", default=None, help="commit to compare with (default: merge-base of HEAD and main)")
    ap.add_argument("--steps", type=int, default=steps, help="measured steps per run")
    ap.add_argument("--warmup", type=int, default=warmup, help="unmeasured steps first (kernel builds, caches)")
    ap.add_argument("--rounds", type=int, default=2, help="alternating baseline/new runs per input (best kept)")
    ap.add_argument("--out", default=None, help="also write the table to this file")
    ap.add_argument("--note", default="", help="one line saying why this run was made (written to --out)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--tree", help=argparse.SUPPRESS)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default="spot,gadget", help="comma-separated folders or names under " + str(SCENES))
    ap.add_argument("--downscale", type=int, default=1, help="dataset downscale factor (1: the images' size)")
    args = comparison_args(ap, worker, steps=20, warmup=3, hidden="--scene")
    if args is None:
        return
    scenes = [resolve_scene(s) for s in args.scenes.split(",") if s]
    base_sha, head = compared_commits(args.baseline)
    lines = []
    with worktree(base_sha) as wt:
        # the machine is shared: load only adds time, so each phase keeps its least disturbed round (the minimum
        # over rounds of the per-round medians)
        res = alternate_rounds(scenes, args.rounds, wt, lambda tree, scene: run_worker(tree, scene, args),
                               lambda r, prev: {k: (min(v, prev[k]) if k in PHASES else v) for k, v in r.items()})
        lines.append(f"# bench/train_step.py  {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}  "
                     f"old = {base_sha[:10]}  new = {head}  steps={args.steps} warmup={args.warmup} "
                     f"rounds={args.rounds} downscale={args.downscale}")
        if args.note:
            lines.append(f"# why: {args.note}")
        lines.append(f"{'scene':<10}{'size':>9}{'faces':>7} {'tree':<5}" + "".join(f"{p:>10}" for p in PHASES)
                     + f"{'psnr':>8}")
        for scene in scenes:
            name = Path(scene).name
            o, n = res[(scene, "old")], res[(scene, "new")]
            for label, r in (("old", o), ("new", n)):
                lines.append(f"{name:<10}{r['size']:>9}{r['faces']:>7} {label:<5}"
                             + "".join(f"{r[p]:>10.2f}" for p in PHASES) + f"{r['psnr_last']:>8.2f}")
            lines.append(f"{name:<10}{'':>9}{'':>7} {'o/n':<5}"
                         + "".join(f"{(o[p] / n[p] if n[p] > 1e-3 else float('nan')):>10.2f}" for p in PHASES))
    write_table("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
