"""A new dev-style scene from a textured OBJ, rendered by Mitsuba 3 (bench only): the object the held-out set may use
that no shipped scene has (the Khronos Avocado of ``../shared/data/gltf``: a textured object whose albedo changes
from region to region, skin / flesh / stone, where every shipped scene is close to one colour).

Why: the dev scenes' albedo is nearly uniform (spot, bob) or a palette on a CAD mesh (gadget), and the external
measurement reported albedo 13-17 dB; a scene with strongly varying albedo shows what the decomposition does there.

    python bench/make_object_scene.py --obj ../shared/data/gltf/avocado/avocado.obj \
        --texture ../shared/data/gltf/avocado/textures/Avocado_baseColor.png --roughness 0.855 --metallic 0 \
        --like ../shared/data/scenes/spot_small --out /tmp/data/scenes/avocado_small
    python bench/make_scene.py /tmp/data/scenes/avocado_small --lights original --out /tmp/avo_original

Writes OUT (a scene folder under ``<root>/scenes/``, its texture copied to ``<root>/meshes/<name>/`` and
``<root>/envmaps`` linked, the layout make_scene.py reads): ``gt_mesh.obj`` / ``gt_mesh.ply`` (the object centred
on its bounding box and scaled so that its farthest vertex is ``--radius`` from the origin, the dev scenes'
normalisation), ``transforms_{train,test}.json`` and the light set of ``--like`` (its cameras and its
``ground_truth.json`` lights), ``ground_truth.json`` (``--roughness``, ``--metallic``, the texture), and
``relight/``: ``albedo/`` (the base colour through each test camera: Mitsuba's ``albedo`` AOV, sRGB-encoded, alpha
the coverage) and the three light sets of ``--like``'s ``relight.json`` rendered with this object. The training
photos then come from make_scene.py (``--lights original`` for ``--like``'s lights, or any of its light sets).
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))


def normalised_obj(src: Path, dst: Path, ply: Path, radius: float) -> dict:
    """``src`` with its vertices centred on their bounding box and scaled to ``radius`` (the UVs, normals and faces
    as they are; material lines dropped), and its triangles as an ASCII PLY; returns the normalisation."""
    lines = src.read_text().splitlines()
    V = np.array([[float(x) for x in ln.split()[1:4]] for ln in lines if ln.startswith("v ")])
    c = 0.5 * (V.min(axis=0) + V.max(axis=0))
    s = radius / float(np.linalg.norm(V - c, axis=1).max())
    V = (V - c) * s
    out, F, k = [], [], 0
    for ln in lines:
        if ln.startswith("v "):
            out.append("v {:.6f} {:.6f} {:.6f}".format(*V[k]))
            k += 1
        elif not ln.startswith(("mtllib", "usemtl")):
            out.append(ln)
            if ln.startswith("f "):
                idx = [int(t.split("/")[0]) - 1 for t in ln.split()[1:]]
                F += [(idx[0], idx[j], idx[j + 1]) for j in range(1, len(idx) - 1)]
    dst.write_text("\n".join(out) + "\n")
    head = (f"ply\nformat ascii 1.0\nelement vertex {len(V)}\nproperty float x\nproperty float y\nproperty float z\n"
            f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n")
    ply.write_text(head + "".join("{:.6f} {:.6f} {:.6f}\n".format(*v) for v in V)
                   + "".join(f"3 {a} {b} {c_}\n" for a, b, c_ in F))
    return {"centre": c.tolist(), "scale": s}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--obj", type=Path, required=True)
    ap.add_argument("--texture", type=Path, required=True, help="the base colour (sRGB)")
    ap.add_argument("--roughness", type=float, required=True)
    ap.add_argument("--metallic", type=float, default=0.0)
    ap.add_argument("--like", type=Path, required=True, help="a shipped scene: its cameras, lights and relight sets")
    ap.add_argument("--out", type=Path, required=True, help="ROOT/scenes/NAME")
    ap.add_argument("--radius", type=float, default=0.92)
    ap.add_argument("--spp", type=int, default=256)
    args = ap.parse_args(argv)

    for lib in ("/usr/lib/x86_64-linux-gnu/libLLVM-19.so", "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"):
        if "DRJIT_LIBLLVM_PATH" not in os.environ and os.path.exists(lib):
            os.environ["DRJIT_LIBLLVM_PATH"] = lib
    import make_scene as ms
    import mitsuba as mi
    import OpenImageIO as oiio

    mi.set_variant("llvm_ad_rgb")
    out, like = args.out.resolve(), args.like.resolve()
    if out.parent.name != "scenes":
        raise SystemExit(f"--out must be ROOT/scenes/NAME (make_scene.py reads the texture from ROOT/meshes), "
                         f"got {out}")
    root = out.parents[1]
    out.mkdir(parents=True, exist_ok=True)
    (root / "meshes" / out.name).mkdir(parents=True, exist_ok=True)
    shutil.copy(args.texture, root / "meshes" / out.name / args.texture.name)
    if not (root / "envmaps").exists():
        (root / "envmaps").symlink_to(like.parents[1] / "envmaps")
    norm = normalised_obj(args.obj, out / "gt_mesh.obj", out / "gt_mesh.ply", args.radius)
    gt = json.loads((like / "ground_truth.json").read_text())
    gt.update(roughness=args.roughness, metallic=args.metallic, texture=args.texture.name, mesh_normalisation=norm,
              source=f"{args.obj.name} (bench/make_object_scene.py), cameras and lights of {like.name}")
    (out / "ground_truth.json").write_text(json.dumps(gt, indent=1))
    for sp in ("train", "test"):
        shutil.copy(like / f"transforms_{sp}.json", out)

    shape = {"type": "obj", "filename": str(out / "gt_mesh.obj"), "face_normals": False,
             "bsdf": {"type": "principled", "roughness": args.roughness, "metallic": args.metallic,
                      "base_color": {"type": "bitmap", "filename": str(args.texture.resolve())}}}
    tj = json.loads((out / "transforms_test.json").read_text())
    fov, res = float(np.degrees(tj["camera_angle_x"])), int(gt["res"])
    adir = out / "relight" / "albedo"
    adir.mkdir(parents=True, exist_ok=True)
    for k, fr in enumerate(tj["frames"]):
        m = np.asarray(fr["transform_matrix"], float) @ np.diag([-1.0, 1.0, -1.0, 1.0])
        d = {"type": "scene", "shape": shape,
             # the AOV (channels 4-6) beside a cheap path image whose alpha (channel 3) is the coverage
             "integrator": {"type": "aov", "aovs": "alb:albedo",
                            "img": {"type": "path", "max_depth": 2, "hide_emitters": True}},
             "sensor": {"type": "perspective", "fov": fov, "fov_axis": "x",
                        "to_world": mi.ScalarTransform4f(m.tolist()),
                        "sampler": {"type": "independent", "sample_count": 64, "seed": k},
                        "film": {"type": "hdrfilm", "width": res, "height": res, "pixel_format": "rgba"}}}
        img = np.asarray(mi.render(mi.load_dict(d)), dtype=np.float64)
        a = np.clip(img[..., 3:4], 0.0, 1.0)
        rgb = np.where(a > 1e-6, img[..., 4:7] / np.maximum(a, 1e-6), 0.0)
        u8 = np.round(np.concatenate([ms.srgb(rgb), a], axis=-1) * 255.0).astype(np.uint8)
        spec = oiio.ImageSpec(res, res, 4, oiio.UINT8)
        spec.attribute("oiio:UnassociatedAlpha", 1)
        name = adir / (Path(fr["file_path"]).name + ".png")
        o = oiio.ImageOutput.create(str(name))
        o.open(str(name), spec)
        o.write_image(u8)
        o.close()
    spec = json.loads((like / "relight" / "relight.json").read_text())
    (out / "relight" / "relight.json").write_text(json.dumps(spec, indent=1))
    base = {"type": "scene", "integrator": {"type": "path", "max_depth": 4, "hide_emitters": True}, "shape": shape}
    ms.render_relight(mi, base, out, root, out, args.spp, None)
    print(f"{out}: {len(tj['frames'])} test views' albedo and relight sets at {res}²", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main())
