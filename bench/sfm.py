"""Benchmark / check: cameras solved by `triplet colmap` against the true cameras of a capture.

Usage::

    python bench/sfm.py DATA [--truth ../shared/data/photos/spot_ground] [--run RUN] [--mesh MESH.ply]

``DATA`` is the output of ``triplet colmap`` (``sparse/0`` undistorted and ``distorted/sparse/0``);
``--truth`` holds ``true_cameras.json`` (NeRF convention) and ``gt_mesh.ply`` (the object in the
same frame): **for checking only**.

Printed, for each solved model (distorted = as solved, undistorted = what training reads):

* registered photos of all photos;
* a similarity transform (Umeyama: scale, rotation, translation) from the solved camera centres to
  the true ones, least squares over the registered photos;
* camera centre error after it: mean / max ``|s·R·c + t − c_true|``, relative to the ring radius
  (the mean distance of the true centres from the vertical line through their look-at point);
* rotation error: the angle of ``R_true⁻¹ · R · R_solved`` (camera-to-world rotations, OpenCV axes),
  mean / max, in degrees.

With ``--mesh`` (e.g. ``RUN/mesh.ply`` of ``triplet train --mesh-stage``): the mesh is mapped by the
same similarity into the true frame and compared with ``gt_mesh.ply`` (symmetric Chamfer, 100k area
samples each way), relative to the cow's radius (the largest distance of a ``gt_mesh`` vertex from
its bounding-box centre). ``--run`` also prints the run's test PSNR (``metrics.json``).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from triplet_cl.camera import quat_to_rotmat
from triplet_cl.datasets.colmap import read_model

DATA = Path(__file__).resolve().parents[2] / "shared" / "data"
GL_TO_CV = np.diag([1.0, -1.0, -1.0])


def true_cameras(truth: Path) -> dict[str, np.ndarray]:
    """``{image name: c2w [4, 4]}`` in OpenCV axes (x right, y down, z forward)."""
    d = json.loads((truth / "true_cameras.json").read_text())
    out = {}
    for fr in d["frames"]:
        m = np.asarray(fr["transform_matrix"], np.float64)
        m[:3, :3] = m[:3, :3] @ GL_TO_CV
        out[Path(fr["file_path"]).name] = m
    return out


def solved_cameras(model_dir: Path) -> tuple[dict[str, np.ndarray], dict]:
    cams, imgs, *_ = read_model(model_dir)
    out = {}
    for im in imgs.values():
        R = quat_to_rotmat(im.qvec)
        c2w = np.eye(4)
        c2w[:3, :3] = R.T
        c2w[:3, 3] = -R.T @ im.tvec
        out[im.name] = c2w
    return out, cams


def umeyama(src: np.ndarray, dst: np.ndarray) -> tuple[float, np.ndarray, np.ndarray]:
    """``(s, R, t)`` minimising ``Σ |s R src + t − dst|²`` (Umeyama 1991)."""
    mu_s, mu_d = src.mean(0), dst.mean(0)
    xs, xd = src - mu_s, dst - mu_d
    cov = xd.T @ xs / len(src)
    U, S, Vt = np.linalg.svd(cov)
    D = np.eye(3)
    if np.linalg.det(U) * np.linalg.det(Vt) < 0:
        D[2, 2] = -1
    R = U @ D @ Vt
    var = (xs ** 2).sum() / len(src)
    s = float(np.trace(np.diag(S) @ D) / var)
    return s, R, mu_d - s * R @ mu_s


def look_at_point(c2ws) -> np.ndarray:
    A, b = np.zeros((3, 3)), np.zeros(3)
    for m in c2ws:
        d = m[:3, 2]
        P = np.eye(3) - np.outer(d, d)
        A += P
        b += P @ m[:3, 3]
    return np.linalg.solve(A, b)


def ring_radius(c2ws) -> float:
    """Mean distance of the centres from the vertical (mean up) line through the look-at point."""
    c = np.array([m[:3, 3] for m in c2ws])
    up = -np.mean([m[:3, 1] for m in c2ws], axis=0)
    up /= np.linalg.norm(up)
    r = c - look_at_point(c2ws)
    r -= np.outer(r @ up, up)
    return float(np.linalg.norm(r, axis=1).mean())


def compare(solved: dict, truth: dict):
    names = sorted(set(solved) & set(truth))
    src = np.array([solved[n][:3, 3] for n in names])
    dst = np.array([truth[n][:3, 3] for n in names])
    s, R, t = umeyama(src, dst)
    cerr = np.linalg.norm((s * (R @ src.T)).T + t - dst, axis=1) / ring_radius([truth[n] for n in names])
    rerr = []
    for n in names:
        M = truth[n][:3, :3].T @ R @ solved[n][:3, :3]
        rerr.append(np.degrees(np.arccos(np.clip((np.trace(M) - 1) / 2, -1, 1))))
    return names, (s, R, t), cerr, np.array(rerr)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("data", type=Path, help="output folder of `triplet colmap`")
    ap.add_argument("--truth", type=Path, default=DATA / "photos" / "spot_ground")
    ap.add_argument("--run", type=Path, help="a training run on DATA (prints its test PSNR)")
    ap.add_argument("--mesh", type=Path, help="an exported mesh (.ply/.obj/.glb) in DATA's frame")
    args = ap.parse_args()
    truth = true_cameras(args.truth)
    sfm = json.loads((args.data / "sfm.json").read_text()) if (args.data / "sfm.json").is_file() else {}
    print(f"{'model':12} {'camera':14} {'registered':>10} {'centre mean':>11} {'centre max':>10} "
          f"{'rot mean':>9} {'rot max':>8}")
    sim = None
    for label, folder in (("distorted", args.data / "distorted" / "sparse" / "0"),
                          ("undistorted", args.data / "sparse" / "0")):
        if not folder.is_dir():
            continue
        solved, cams = solved_cameras(folder)
        names, sim_k, cerr, rerr = compare(solved, truth)
        sim = sim or sim_k
        model = ",".join(sorted({c.model for c in cams.values()}))
        print(f"{label:12} {model:14} {len(names):>4} of {len(truth):<3} {100 * cerr.mean():>10.3f}% "
              f"{100 * cerr.max():>9.3f}% {rerr.mean():>8.3f}° {rerr.max():>7.3f}°")
    if sfm:
        print(f"SfM: {sfm['registered']} of {sfm['photos']} registered, {sfm['points']} points, reprojection "
              f"{sfm['mean_reprojection_error_px']:.3f} px, camera {sfm['camera']['model']} "
              f"{[round(x, 5) for x in sfm['camera']['params']]}")
        print("SfM time: " + ", ".join(f"{k[:-2]} {sfm[k]:.1f} s" for k in
                                       ("features_s", "matching_s", "mapping_s", "undistortion_s", "total_s"))
              + f"; CPU {sfm['cpu_s']:.1f} s")
    if args.run is not None and (args.run / "metrics.json").is_file():
        m = json.loads((args.run / "metrics.json").read_text())
        print(f"run {args.run}: test PSNR {m['psnr']:.2f} dB, SSIM {m['ssim']:.4f} ({m.get('iterations')} it., "
              f"{m.get('faces')} faces)")
        mm = args.run / "mesh_metrics.json"
        if mm.is_file():
            print(f"mesh metrics: {json.loads(mm.read_text())}")
    if sim is not None and (args.truth / "gt_mesh.ply").is_file():
        # the automatic region of interest of the mesh stage (mesh/roi.py) against the true cow, in DATA's frame
        import trimesh

        from triplet_cl.datasets import load_dataset
        from triplet_cl.mesh.roi import auto_roi

        s, R, t = sim
        ds = load_dataset(args.data, downscale=4)
        roi = auto_roi([v.camera for v in ds.train], ds.points)
        g = np.asarray(trimesh.load(args.truth / "gt_mesh.ply", process=False, force="mesh").vertices, np.float64)
        g_data = ((g - t) @ R) / s  # true frame -> DATA's frame
        if roi is None:
            print("auto ROI: none found")
        else:
            inside = roi.contains(g_data).mean()
            gl = roi.local(g_data)
            print(f"auto ROI: half sizes {np.round(roi.half * s, 3).tolist()} (true units), ground plane "
                  f"{'found' if roi.ground is not None else 'none'}; holds {100 * inside:.1f} % of gt_mesh's vertices; "
                  f"cow extent along the box axes {np.round((gl.max(0) - gl.min(0)) * s, 3).tolist()}")
    if args.mesh is not None and sim is not None:
        import trimesh

        from triplet_cl.mesh.metrics import chamfer_distance

        s, R, t = sim
        m = trimesh.load(args.mesh, process=False, force="mesh")
        V = (s * (R @ np.asarray(m.vertices, np.float64).T)).T + t
        g = trimesh.load(args.truth / "gt_mesh.ply", process=False, force="mesh")
        Vg = np.asarray(g.vertices, np.float64)
        radius = float(np.linalg.norm(Vg - 0.5 * (Vg.min(0) + Vg.max(0)), axis=1).max())
        c = chamfer_distance(V, np.asarray(m.faces), Vg, np.asarray(g.faces))
        print(f"mesh {args.mesh}: {len(m.faces)} faces; Chamfer to gt_mesh {c['chamfer'] / radius:.4f} of the cow's "
              f"radius ({radius:.3f}; mesh→gt {c['d12'] / radius:.4f}, gt→mesh {c['d21'] / radius:.4f}, "
              f"hausdorff90 {c['hausdorff90'] / radius:.4f})")


if __name__ == "__main__":
    main()
