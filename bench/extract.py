"""Benchmark: soup → mesh extraction, TSDF fusion vs vertex welding, on the shared scenes.

Usage: ``python bench/extract.py [--scenes spot bob_env] [--data ../shared/data] [--resolution 128]
[--runs ../runs] [--device SPEC]`` (resolution default: automatic, a voxel of 1.25 pixels).

The soup is a proxy for a trained one, made from the scene's ``gt_mesh.ply`` (the object
normalised into the unit sphere, so distances below are in units of the object radius):

* ``split``: every face a separate triangle, vertices jittered by N(0, σ = 0.002), per-vertex alpha
  ``sigmoid(logit(0.9) + N(0, 0.5))``, plus 5 % junk faces (alpha 0.03) scattered in the bounds;
* ``gappy``: the same, with every triangle also shrunk by 10 % towards its centroid — trained
  triplets do not share vertices, they overlap or leave gaps;
* ``random``: what a trained soup looks like — 3× as many independent equilateral triangles as
  the mesh has faces, centred on area-uniform surface samples, lying in the tangent plane with a
  random rotation, radius 1.2 × the sample spacing (they overlap), same alpha noise and junk.

Where ``RUNS/<scene>`` holds a training run, the soup of its latest checkpoint is measured too
(depth rendered with the run's soft-coverage ``sigma``, as it was trained), and again with the
photos' alpha masks (``trained+m``: free-space carving and the visual hull, as the mesh stage).

Each method's mesh is compared with ``gt_mesh.ply``: symmetric mean Chamfer distance (100k area
samples each way, ``triplet_cl.mesh.metrics``), face count, watertightness, connected components,
wall time. Depth is rendered at the dataset's resolution from all training views; the proxies with
hard edges (``sigma=None``: their alphas were not trained against a soft window).
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import numpy as np

from triplet_cl import get_device
from triplet_cl.datasets import load_dataset
from triplet_cl.mesh.extract import extract_mesh, mesh_stats
from triplet_cl.mesh.metrics import chamfer_distance, load_reference_mesh
from triplet_cl.scene import Scene, logit

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
RUNS = Path(__file__).resolve().parents[2] / "runs"


def proxy_soup(V, F, rng, jitter=0.002, shrink=0.0, junk=0.05) -> Scene:
    """A soup from a reference mesh: split faces, jitter, alpha noise, junk faces (module docstring)."""
    T = V[F].astype(np.float64)  # [M, 3, 3]
    if shrink:
        c = T.mean(axis=1, keepdims=True)
        T = c + (1 - shrink) * (T - c)
    T = T + rng.normal(scale=jitter, size=T.shape)
    n_junk = int(junk * len(F))
    lo, hi = V.min(0), V.max(0)
    centre = rng.uniform(lo, hi, size=(n_junk, 1, 3))
    J = centre + rng.normal(scale=0.02, size=(n_junk, 3, 3))
    Vs = np.concatenate([T, J]).reshape(-1, 3)
    alpha = np.concatenate([logit(0.9) + rng.normal(scale=0.5, size=3 * len(F)), np.full(3 * n_junk, logit(0.03))])
    return Scene.from_arrays(Vs, np.arange(len(Vs)).reshape(-1, 3), alpha=alpha[:, None])


def random_soup(V, F, rng, factor=3.0, junk=0.05) -> Scene:
    """Independent tangent triangles on surface samples (the ``random`` proxy, module docstring)."""
    import trimesh

    m = trimesh.Trimesh(V, F, process=False)
    n = int(factor * len(F))
    P, fi = trimesh.sample.sample_surface(m, n, seed=int(rng.integers(1 << 31)))
    N = m.face_normals[fi]
    r = 1.2 * np.sqrt(m.area / n)
    a = np.cross(N, rng.normal(size=(n, 3)))
    a /= np.linalg.norm(a, axis=1, keepdims=True)
    b = np.cross(N, a)
    ang = np.array([0.0, 2 * np.pi / 3, 4 * np.pi / 3])
    T = P[:, None] + r * (np.cos(ang)[None, :, None] * a[:, None] + np.sin(ang)[None, :, None] * b[:, None])
    n_junk = int(junk * n)
    J = rng.uniform(V.min(0), V.max(0), size=(n_junk, 1, 3)) + rng.normal(scale=0.02, size=(n_junk, 3, 3))
    Vs = np.concatenate([T, J]).reshape(-1, 3)
    alpha = np.concatenate([logit(0.9) + rng.normal(scale=0.5, size=3 * n), np.full(3 * n_junk, logit(0.03))])
    return Scene.from_arrays(Vs, np.arange(len(Vs)).reshape(-1, 3), alpha=alpha[:, None])


def load_run_soup(run: Path, data: Path):
    """``(soup, sigma)`` of a training run's latest checkpoint, or None when it has none."""
    from triplet_cl.train import Trainer

    if not (run / "checkpoints" / "latest").is_file():
        return None
    try:
        tr = Trainer(str(data), run, resume=True, quiet=True)
    except (FileNotFoundError, ValueError) as exc:
        print(f"  (run {run}: {exc})")
        return None
    return tr.scene, tr.cfg.sigma


def measure(name, soup, cams, ref, method, args, dev, sigma=None, masks=None) -> dict:
    t0 = time.perf_counter()
    try:
        A = extract_mesh(soup, cams, method=method, resolution=args.resolution, sigma=sigma, device=dev, masks=masks)
    except ValueError as exc:
        print(f"  {name:8s} {method:5s} failed: {exc}")
        return {}
    wall = time.perf_counter() - t0
    st = mesh_stats(A.V, A.F)
    cd = chamfer_distance(A.V, A.F, ref[0], ref[1], n=100_000)
    row = {"soup": name, "method": method, "chamfer": cd["chamfer"], "h90": cd["hausdorff90"], **st, "time_s": wall}
    print(f"  {name:8s} {method:5s} {row['chamfer']:9.5f} {row['h90']:9.5f} {st['faces']:8d} "
          f"{str(st['watertight']):>6s} {st['components']:6d} {wall:8.1f}", flush=True)
    return row


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", nargs="+", default=["spot", "bob_env"])
    ap.add_argument("--data", type=Path, default=DATA)
    ap.add_argument("--resolution", type=int, default=None, help="TSDF grid resolution (default: automatic)")
    ap.add_argument("--runs", type=Path, default=RUNS, help="folder of training runs named after the scenes")
    ap.add_argument("--device", default=None)
    args = ap.parse_args()
    dev = get_device(args.device)
    rng = np.random.default_rng(0)
    print(f"device: {dev.name}; TSDF resolution {args.resolution or 'auto (voxel = 1.25 px)'}")
    for scene_name in args.scenes:
        root = args.data / "scenes" / scene_name
        ds = load_dataset(root)
        cams = ds.cameras("train")
        ref = load_reference_mesh(root)
        floor = chamfer_distance(ref[0], ref[1], ref[0], ref[1], n=100_000, seed=7)["chamfer"]
        print(f"\n{scene_name}: {len(ref[1])} gt faces, {len(cams)} views {cams[0].width}x{cams[0].height}; "
              f"Chamfer of gt against itself (sampling floor) {floor:.5f}")
        print(f"  {'soup':8s} {'meth':5s} {'chamfer':>9s} {'h90':>9s} {'faces':>8s} {'closed':>6s} {'comps':>6s} "
              f"{'time_s':>8s}")
        soups = {"split": proxy_soup(ref[0], ref[1], rng), "gappy": proxy_soup(ref[0], ref[1], rng, shrink=0.1),
                 "random": random_soup(ref[0], ref[1], rng)}
        sigmas = {}
        run = load_run_soup(args.runs / scene_name, root)
        if run is not None:
            soups["trained"], sigmas["trained"] = run
        for name, soup in soups.items():
            for method in ("tsdf", "weld"):
                measure(name, soup, cams, ref, method, args, dev, sigmas.get(name))
        if run is not None and ds.has_alpha:  # as the mesh stage: the photos' alpha carves, visual hull
            masks = [v.alpha for v in ds.train]
            measure("trained+m", soups["trained"], cams, ref, "tsdf", args, dev, sigmas["trained"], masks=masks)


if __name__ == "__main__":
    main()
