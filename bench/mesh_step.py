"""Benchmark: one refinement step of the mesh stage, this tree beside an older commit.

Usage::

    python bench/mesh_step.py --runs RUN[,RUN ...] [--baseline COMMIT] [--steps 40] [--warmup 5] [--rounds 2]
                              [--pixel-sigma 0.5] [--out bench/results/NAME.txt] [--note "why"]

Each RUN is a trained soup (``triplet train``'s folder). For every run and tree, a fresh subprocess copies the run to a
temporary folder, resumes its trainer, extracts the mesh with that tree's ``MeshStage.extract`` (so each tree meshes
and renders the soup its own way: opacity, pruning) and runs ``MeshStage.refine`` as a later round (no AO choice,
metallic trial or light fit, which are not per-step costs) for ``--warmup`` + ``--steps`` steps with no remesh, the
capture's pixel filter fixed at ``--pixel-sigma`` for both trees; the step time is the stage's own per-step record
(render, loss, backward, regularisers, Adam). Baseline and this tree alternate ``--rounds`` times (the machine is
shared: the least loaded round of each is kept). The baseline is checked out into a temporary worktree and imported
through ``bench/train_step.py``'s shim. Default baseline: the merge-base of ``HEAD`` and ``main``.
"""

from __future__ import annotations

import argparse
import json
import shutil
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_step import (  # noqa: E402  (a sibling script)
    alternate_rounds,
    compared_commits,
    comparison_args,
    import_tree,
    run_script_worker,
    worktree,
    write_table,
)


def worker(args) -> None:
    tree = Path(args.tree).resolve()
    import_tree(tree)
    from dataclasses import replace

    import numpy as np

    from triplet_cl import train as train_mod
    from triplet_cl.mesh import refine as refine_mod

    assert Path(refine_mod.__file__).resolve().is_relative_to(tree), refine_mod.__file__
    with tempfile.TemporaryDirectory(prefix="mesh_step_") as d:
        run = Path(d) / "run"
        shutil.copytree(args.run, run, ignore=shutil.ignore_patterns("renders", "mesh*", "*.tmp"))
        tr = train_mod.Trainer(None, run, resume=True, quiet=True)
        n = args.warmup + args.steps
        cfg = replace(refine_mod.MeshConfig(), iterations=n, remesh_every=0, pixel_sigma=args.pixel_sigma)
        st = refine_mod.MeshStage(tr, cfg, quiet=True)
        scene = st.extract(tr.scene)
        t0 = time.perf_counter()
        st.refine(scene, 1)
        wall = time.perf_counter() - t0
        times = [h["time"] for h in st.history[args.warmup:]]
        cam = tr.ds.train[0].camera
        out = {"step": 1e3 * float(np.median(times)), "step_min": 1e3 * float(np.min(times)), "wall": wall,
               "faces": len(scene.F), "size": f"{cam.width}x{cam.height}", "supersample": cfg.supersample,
               "psnr_last10": float(np.mean([h["psnr"] for h in st.history[-10:]]))}
    print("RESULT " + json.dumps(out))


def run_worker(tree: Path, run: str, args) -> dict:
    return run_script_worker(__file__, tree, run, ["--run", run, "--steps", str(args.steps), "--warmup",
                                                   str(args.warmup), "--pixel-sigma", str(args.pixel_sigma)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", default=None, help="comma-separated trained run folders (required)")
    ap.add_argument("--pixel-sigma", type=float, default=0.5, help="the capture's pixel filter, for both trees")
    args = comparison_args(ap, worker, steps=40, warmup=5, hidden="--run")
    if args is None:
        return
    if not args.runs:
        raise SystemExit("mesh_step.py: error: give --runs RUN[,RUN ...] (trained soups)")
    runs = [str(Path(r).resolve()) for r in args.runs.split(",") if r]
    for r in runs:
        if not (Path(r) / "config.json").is_file():
            raise SystemExit(f"mesh_step.py: error: {r} is not a trained run (no config.json)")
    base_sha, head = compared_commits(args.baseline)
    lines = []
    with worktree(base_sha) as wt:
        res = alternate_rounds(runs, args.rounds, wt, lambda tree, run: run_worker(tree, run, args),
                               lambda r, prev: r if r["step"] < prev["step"] else prev)
        lines.append(f"# bench/mesh_step.py  {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}  "
                     f"old = {base_sha[:10]}  new = {head}  steps={args.steps} warmup={args.warmup} "
                     f"rounds={args.rounds} pixel_sigma={args.pixel_sigma}")
        if args.note:
            lines.append(f"# why: {args.note}")
        lines.append(f"{'run':<16}{'size':>9}{'faces':>7} {'tree':<5}{'step ms':>9}{'min ms':>9}{'psnr':>8}")
        for run in runs:
            name = Path(run).name[:15]
            o, n = res[(run, "old")], res[(run, "new")]
            for label, r in (("old", o), ("new", n)):
                lines.append(f"{name:<16}{r['size']:>9}{r['faces']:>7} {label:<5}{r['step']:>9.2f}{r['step_min']:>9.2f}"
                             f"{r['psnr_last10']:>8.2f}")
            lines.append(f"{name:<16}{'':>9}{'':>7} {'o/n':<5}{o['step'] / n['step']:>9.2f}"
                         f"{o['step_min'] / n['step_min']:>9.2f}")
    write_table("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
