"""Benchmark: the traces of the cached visibility on a refined mesh, this tree beside an older commit.

Usage::

    python bench/visibility_cost.py RUN [RUN ...] [--baseline COMMIT] [--rounds 2] [--out bench/results/NAME.txt]

For every run with a refined mesh (``mesh_stage.npz``; its scene's ``transforms_train.json`` gives the cameras) the
traces the mesh stage makes, each timed alone (best of ``--steps`` calls after ``--warmup``), in a fresh process
per tree, alternating the baseline's tree and this one ``--rounds`` times (``train_step.py``'s machinery):

- ``light``: :func:`~triplet_cl.visibility.vertex_visibility` towards the run's own lights (the cast shadows);
- ``ao``: :func:`~triplet_cl.visibility.vertex_occlusion` with 64 directions and degree 2 (the ambient occlusion and
  the environment's occlusion come from this one trace);
- ``cameras``: visibility towards every training camera's centre (the light fit's "which view sees which vertex"),
  with the vertices' normals where this tree's ``vertex_visibility`` takes them (the mesh stage passes them).

Milliseconds, and the old / new ratio; the largest absolute difference of the returned values (``max |d|``: the
early-out of ``trace.cl`` moves a value by less than 1e-4; for the AO trace, of ``ao`` and ``ao · U``, what the
shading reads; for the cameras, only where a camera is in front of the vertex, the rows the light fit reads).
"""

from __future__ import annotations

import argparse
import inspect
import json
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
from train_step import (  # noqa: E402
    alternate_rounds,
    compared_commits,
    comparison_args,
    import_tree,
    run_script_worker,
    worktree,
    write_table,
)

TRACES = ("light", "ao", "cameras")


def worker(args) -> None:
    tree = Path(args.tree).resolve()
    import_tree(tree)
    from triplet_cl.lights import PointLight
    from triplet_cl.mesh.bake import vertex_normals
    from triplet_cl.mesh.refine import MESH_STATE, load_mesh_state
    from triplet_cl.visibility import vertex_occlusion, vertex_visibility

    run = Path(args.run)
    scene = load_mesh_state(run / MESH_STATE)
    data = Path(json.loads((run / "config.json").read_text())["data"])
    frames = json.loads((data / "transforms_train.json").read_text())["frames"]
    centres = [np.asarray(f["transform_matrix"], np.float64)[:3, 3] for f in frames]
    V = np.asarray(scene.V.data, np.float64)
    nrm = vertex_normals(V, scene.F)
    takes_normals = "normals" in inspect.signature(vertex_visibility).parameters
    cams = [PointLight(c, np.ones(3)) for c in centres]
    calls = {"light": lambda: vertex_visibility(scene, ray_eps=0.03),
             "ao": lambda: np.concatenate([np.reshape(a, (len(V), -1)) for a in vertex_occlusion(scene, nrm, None, 64,
                                                                                                  2, 0.03)], 1),
             "cameras": (lambda: vertex_visibility(scene, lights=cams, ray_eps=0.03, normals=nrm)) if takes_normals
             else (lambda: vertex_visibility(scene, lights=cams, ray_eps=0.03))}
    out, values = {}, {}
    for name in TRACES:
        ts = []
        for i in range(args.warmup + args.steps):
            t0 = time.perf_counter()
            v = calls[name]()
            if i >= args.warmup:
                ts.append(time.perf_counter() - t0)
        out[name] = 1e3 * min(ts)
        values[name] = np.asarray(v, np.float64)
    front = np.stack([(nrm * (c - V)).sum(1) > 0 for c in centres], 1)
    np.savez(args.values, front=front, **values)
    out.update(vertices=len(V), faces=len(scene.F), views=len(centres), normals=takes_normals)
    print("RESULT " + json.dumps(out))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="*", help="run directories with a refined mesh")
    ap.add_argument("--values", help=argparse.SUPPRESS)  # the worker's output of the traced values
    args = comparison_args(ap, worker, steps=3, warmup=1, hidden="--run")
    if args is None:
        return
    base_sha, head = compared_commits(args.baseline)
    tmp = Path(tempfile.mkdtemp(prefix="visibility_cost_"))
    runs = [str(Path(r).resolve()) for r in args.runs]

    def run(tree, r):
        label = "old" if tree != Path(__file__).resolve().parents[1] else "new"
        vals = tmp / f"{Path(r).name}_{label}.npz"
        res = run_script_worker(__file__, tree, r, ["--run", r, "--values", str(vals), "--steps", str(args.steps),
                                                    "--warmup", str(args.warmup)])
        res["values"] = str(vals)
        return res

    with worktree(base_sha) as wt:
        res = alternate_rounds(runs, args.rounds, wt, run,
                               lambda r, prev: {k: (min(v, prev[k]) if k in TRACES else v) for k, v in r.items()})
        lines = [f"# bench/visibility_cost.py  {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}  old = "
                 f"{base_sha[:10]}  new = {head}  steps={args.steps} warmup={args.warmup} rounds={args.rounds}"]
        if args.note:
            lines.append(f"# why: {args.note}")
        lines += ["| run | vertices / faces / views | trace | old ms | new ms | old / new | max abs d |",
                  "|---|---|---|---|---|---|---|"]
        for r in runs:
            o, n = res[(r, "old")], res[(r, "new")]
            vo, vn = np.load(o["values"]), np.load(n["values"])
            for name in TRACES:
                a, b = vo[name], vn[name]
                if name == "ao":  # the shading reads ao and ao · U (U alone is ill-defined where ao ~ 0)
                    a, b = np.concatenate([a[:, :1], a[:, :1] * a[:, 1:]], 1), np.concatenate([b[:, :1], b[:, :1] *
                                                                                             b[:, 1:]], 1)
                d = np.abs(a - b)
                if name == "cameras":
                    d = d[vn["front"]]
                lines.append(f"| {Path(r).name} | {n['vertices']} / {n['faces']} / {n['views']} | {name} | "
                             f"{o[name]:.0f} | {n[name]:.0f} | {o[name] / n[name]:.2f} | {d.max():.1e} |")
    write_table("\n".join(lines), args.out)


if __name__ == "__main__":
    main()
