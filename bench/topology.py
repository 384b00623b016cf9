"""Topology of the mesh stage's extraction with and without the exact visual-hull rule (issue 21: webbing
between spot's legs, genus 3 for a genus-0 cow), and the Chamfer distance to the dataset's gt_mesh.ply.

Extraction only (``MeshConfig(iterations=0)``, as ``triplet extract RUN --mesh-iterations 0`` but nothing
written into the run), for each value of ``tsdf_fusion``'s ``hull_exact_views`` (``none``: off, the rule
before; 1: the default). The run is only read.

    .venv/bin/python bench/topology.py RUN [--hull-exact-views none 1 2 3]
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

import triplet_cl.mesh.extract as ex
from triplet_cl.mesh.metrics import chamfer_distance, load_reference_mesh
from triplet_cl.mesh.refine import MeshConfig, MeshStage
from triplet_cl.mesh.repair import mesh_topology
from triplet_cl.train import Trainer


def main() -> None:
    ap = argparse.ArgumentParser()
    ap.add_argument("run")
    ap.add_argument("--hull-exact-views", nargs="+", default=["none", "1"])
    a = ap.parse_args()
    tr = Trainer(None, Path(a.run), resume=True, quiet=True)
    ref = load_reference_mesh(tr.data)
    stage = MeshStage(tr, MeshConfig(iterations=0))
    orig = ex.tsdf_fusion
    print(f"{a.run} ({tr.data}): extraction only")
    print(f"{'exact':>5} {'faces':>6} {'genus':>5} {'closed':>6} {'crossing':>8} {'chamfer':>8} {'h90':>7} {'s':>4}")
    for text in a.hull_exact_views:
        hev = None if text == "none" else int(text)

        def patched(*args, _hev=hev, **kw):
            kw["hull_exact_views"] = _hev
            return orig(*args, **kw)

        ex.tsdf_fusion = patched
        t = time.perf_counter()
        sc = stage.extract(tr.scene)
        V, F = np.asarray(sc.V.data, np.float64), np.asarray(sc.F)
        top = mesh_topology(V, F)
        cd = chamfer_distance(V, F, *ref) if ref is not None else {"chamfer": float("nan"), "hausdorff90": float("nan")}
        print(f"{text:>5} {top['faces']:6d} {str(top['genus']):>5} {str(top['watertight']):>6} "
              f"{top['self_intersections']:8d} {cd['chamfer']:8.5f} {cd['hausdorff90']:7.4f} "
              f"{time.perf_counter() - t:4.0f}", flush=True)
    ex.tsdf_fusion = orig


if __name__ == "__main__":
    main()
