"""Mesh-stage variants on one trained soup (issue 19): the extraction once (cached), then the refinement, the
repair and the evaluation for each set of ``MeshConfig`` overrides, with the mesh before the repair kept.

    python bench/mesh_variants.py RUN_COPY NAME [field=value ...] [--out DIR]
    python bench/mesh_variants.py RUN_COPY NAME laplacian=uniform repair_rings=2   # the rules before
    python bench/mesh_variants.py --parts DIR/gadget_a DIR/gadget_b                 # per-part survival (gadget)

``RUN_COPY``: a copy of a trained run (its ``train.log`` gets the stage's log lines; nothing else is written
there). Each variant writes ``DIR/RUNNAME_NAME/{mesh_stage.npz, mesh_pre_repair.npz, res.json}`` and prints
the test PSNR (at the stage's eval supersampling), Chamfer to ``gt_mesh.ply``, faces, genus and wall times.
``--parts``: for the gadget scene, the fraction of each ground-truth part's surface (parts: connected
components of ``gt_mesh.ply``, grouped by their oriented-box extents) within 1 % / 2 % of the radius of each
mesh, and F1 at 1 %. ``gt_mesh.ply`` is only read to measure, never as an input of the stage.
"""

from __future__ import annotations

import argparse
import dataclasses
import json
import time
from pathlib import Path

import numpy as np


def _value(v: str):
    if v == "None":
        return None
    for cast in (int, float):
        try:
            return cast(v)
        except ValueError:
            pass
    return v


def run_variant(run: Path, name: str, over: dict, out_root: Path) -> dict:
    from triplet_cl.device import get_device
    from triplet_cl.mesh.metrics import chamfer_distance, load_reference_mesh
    from triplet_cl.mesh.refine import MeshConfig, MeshStage, load_mesh_state, save_mesh_state
    from triplet_cl.train import Trainer

    cfg = dataclasses.replace(MeshConfig(), **over)
    t0 = time.time()
    tr = Trainer(None, run, device=get_device(None), resume=True, quiet=True)
    st = MeshStage(tr, cfg, quiet=True)
    key = f"{run.name}_r{cfg.resolution}_f{cfg.extract_faces}_q{cfg.depth_quantile}_h{cfg.photo_hull}"
    cache = out_root / f"extract_{key}.npz"
    if cache.is_file():
        scene = load_mesh_state(cache)
    else:
        scene = st.extract(tr.scene)
        save_mesh_state(cache, scene, cfg)
    t1 = time.time()
    if cfg.iterations:
        scene = st.refine(scene, 0)
    t2 = time.time()
    st.scene = scene
    out = out_root / f"{run.name}_{name}"
    out.mkdir(parents=True, exist_ok=True)
    save_mesh_state(out / "mesh_pre_repair.npz", scene, cfg)
    topo = st.repair()
    save_mesh_state(out / "mesh_stage.npz", scene, cfg)
    ev = st._evaluate_scene(scene, write_renders=False)
    ref = load_reference_mesh(tr.data)
    cd = chamfer_distance(scene.V.data, scene.F, *ref) if ref is not None else {}
    res = {"name": name, "over": over, "psnr": ev["psnr"], "faces": len(scene.F), **cd,
           "t_extract": t1 - t0, "t_refine": t2 - t1, "t_total": time.time() - t0,
           "genus": topo["after_repair"].get("genus"), "per_view": [round(v["psnr"], 2) for v in ev["views"]]}
    (out / "res.json").write_text(json.dumps(res))
    return res


def parts_table(dirs: list[str], data: str) -> None:
    import trimesh
    from scipy.spatial import cKDTree

    from triplet_cl.mesh.metrics import sample_surface

    m = trimesh.load(Path(data) / "gt_mesh.ply", process=False)
    V, F = np.asarray(m.vertices, np.float64), np.asarray(m.faces)
    pg = sample_surface(V, F, 100_000, seed=1)
    tri = V[F]
    area = 0.5 * np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1)
    fid = np.random.default_rng(1).choice(len(F), size=100_000, p=area / area.sum())  # as sample_surface's faces
    comps = trimesh.graph.connected_components(m.face_adjacency, nodes=np.arange(len(F)), min_len=1)
    lab = np.zeros(len(F), int)
    for i, c in enumerate(comps):
        lab[c] = i
    groups: dict = {}
    for i, c in enumerate(comps):
        e = np.sort(m.submesh([c], append=True).bounding_box_oriented.primitive.extents)
        groups.setdefault(tuple(float(x) for x in np.round(e, 3)), []).append(i)
    res = {}
    for d in dirs:
        z = np.load(Path(d) / "mesh_stage.npz")
        pm = sample_surface(z["V"], z["F"], 100_000, seed=0)
        d21 = cKDTree(pm).query(pg)[0]
        d12 = cKDTree(pg).query(pm)[0]
        p, r = (d12 < 0.01).mean(), (d21 < 0.01).mean()
        print(f"{d}: F1@1% {2 * p * r / (p + r):.3f} (precision {p:.3f}, recall {r:.3f}), "
              f"Chamfer {0.5 * (d12.mean() + d21.mean()):.5f}")
        res[d] = d21
    print("gt part (sorted extents)   n   " + "  ".join(Path(d).name for d in dirs))
    for key, ids in sorted(groups.items()):
        sel = np.isin(lab[fid], ids)
        print(f"{str(key):26s} {len(ids):2d}  " + "  ".join(f"{(x[sel] < 0.01).mean():.2f}/{(x[sel] < 0.02).mean():.2f}"
                                                        for x in res.values()))


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("args", nargs="+", help="RUN_COPY NAME [field=value ...], or with --parts: result folders")
    ap.add_argument("--out", default="/tmp/mesh_variants", help="results folder (default /tmp/mesh_variants)")
    ap.add_argument("--parts", action="store_true", help="per-part survival table of result folders (gadget)")
    ap.add_argument("--data", default="../shared/data/scenes/gadget", help="the dataset of --parts")
    a = ap.parse_args()
    if a.parts:
        parts_table(a.args, a.data)
        return
    run, name, *kv = a.args
    over = {k: _value(v) for k, v in (x.split("=", 1) for x in kv)}
    out = Path(a.out)
    out.mkdir(parents=True, exist_ok=True)
    res = run_variant(Path(run), name, over, out)
    print(json.dumps({k: (round(v, 5) if isinstance(v, float) else v) for k, v in res.items() if k != "per_view"}))


if __name__ == "__main__":
    main()
