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
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_step import ROOT, default_baseline, git, import_tree  # noqa: E402  (a sibling script)


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
    cmd = [sys.executable, str(Path(__file__).resolve()), "--worker", "--tree", str(tree), "--run", run,
           "--steps", str(args.steps), "--warmup", str(args.warmup), "--pixel-sigma", str(args.pixel_sigma)]
    env = dict(os.environ, PYTHONDONTWRITEBYTECODE="1")
    p = subprocess.run(cmd, capture_output=True, text=True, env=env, cwd=tempfile.gettempdir())
    for line in p.stdout.splitlines():
        if line.startswith("RESULT "):
            return json.loads(line[7:])
    raise RuntimeError(f"worker failed on {tree} / {run} (exit {p.returncode}):\n{p.stderr[-3000:]}")


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--runs", default=None, help="comma-separated trained run folders (required)")
    ap.add_argument("--baseline", default=None, help="commit to compare with (default: merge-base of HEAD and main)")
    ap.add_argument("--steps", type=int, default=40, help="measured steps per run")
    ap.add_argument("--warmup", type=int, default=5, help="unmeasured steps first (kernel builds, caches)")
    ap.add_argument("--rounds", type=int, default=2, help="alternating baseline/new runs per soup (best kept)")
    ap.add_argument("--pixel-sigma", type=float, default=0.5, help="the capture's pixel filter, for both trees")
    ap.add_argument("--out", default=None, help="also write the table to this file")
    ap.add_argument("--note", default="", help="one line saying why this run was made (written to --out)")
    ap.add_argument("--worker", action="store_true", help=argparse.SUPPRESS)
    ap.add_argument("--tree", help=argparse.SUPPRESS)
    ap.add_argument("--run", help=argparse.SUPPRESS)
    args = ap.parse_args()
    if args.worker:
        worker(args)
        return
    if not args.runs:
        raise SystemExit("mesh_step.py: error: give --runs RUN[,RUN ...] (trained soups)")
    runs = [str(Path(r).resolve()) for r in args.runs.split(",") if r]
    for r in runs:
        if not (Path(r) / "config.json").is_file():
            raise SystemExit(f"mesh_step.py: error: {r} is not a trained run (no config.json)")
    base = args.baseline or default_baseline()
    base_sha = git("rev-parse", "--verify", base + "^{commit}")
    head = git("rev-parse", "--short", "HEAD") + ("+dirty" if git("status", "--porcelain", "--untracked-files=no")
                                                  else "")
    tmp = Path(tempfile.mkdtemp(prefix="triplet_base_"))
    wt = tmp / "tree"
    git("worktree", "add", "--detach", str(wt), base_sha)
    lines = []
    try:
        res = {}
        for run in runs:
            for _ in range(args.rounds):
                for label, tree in (("old", wt), ("new", ROOT)):
                    r = run_worker(tree, run, args)
                    prev = res.get((run, label))
                    res[(run, label)] = r if prev is None or r["step"] < prev["step"] else prev
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
    finally:
        git("worktree", "remove", "--force", str(wt))
        try:
            tmp.rmdir()
        except OSError:
            pass
    text = "\n".join(lines)
    print(text)
    if args.out:
        out = Path(args.out)
        out.parent.mkdir(parents=True, exist_ok=True)
        tmp_out = out.with_suffix(out.suffix + ".tmp")
        tmp_out.write_text(text + "\n")
        tmp_out.replace(out)


if __name__ == "__main__":
    main()
