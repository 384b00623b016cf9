"""Tiny synthetic datasets for the dataset tests: PNGs via OpenImageIO, NeRF / instant-ngp
``transforms*.json`` and COLMAP sparse models in text and binary (a small writer of COLMAP's
binary format lives here, independent of the reader under test)."""

from __future__ import annotations

import json
import struct
from pathlib import Path

import numpy as np
import OpenImageIO as oiio
from scipy.spatial.transform import Rotation

W, H = 8, 6
MODEL_IDS = {"SIMPLE_PINHOLE": 0, "PINHOLE": 1, "SIMPLE_RADIAL": 2, "RADIAL": 3, "OPENCV": 4, "OPENCV_FISHEYE": 5}


# ---- images -------------------------------------------------------------------------------------------
def write_image(path, pixels, dtype: str = "uint8") -> Path:
    """Write ``[H, W, C]`` float pixels as they are (straight alpha) with OpenImageIO."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    px = np.ascontiguousarray(pixels, dtype=np.float32)
    if px.ndim == 2:
        px = px[:, :, None]
    spec = oiio.ImageSpec(px.shape[1], px.shape[0], px.shape[2], dtype)
    spec.attribute("oiio:UnassociatedAlpha", 1)
    out = oiio.ImageOutput.create(str(path))
    assert out is not None, oiio.geterror()
    assert out.open(str(path), spec), out.geterror()
    assert out.write_image(px), out.geterror()
    out.close()
    return path


def image_pixels(index: int, w: int = W, h: int = H, alpha: bool = True) -> np.ndarray:
    """Distinct, 8-bit-exact pixels for image ``index``: colour ramps, alpha from 0 to 1."""
    yy, xx = np.mgrid[0:h, 0:w]
    r = (xx * 17 + index * 5) % 256
    g = (yy * 29 + index * 11) % 256
    b = (xx * yy * 7 + index * 3) % 256
    chans = [r, g, b]
    if alpha:
        chans.append((xx + yy * w) * 255 // (w * h - 1))
    return (np.stack(chans, axis=-1) / 255.0).astype(np.float32)


# ---- poses ----------------------------------------------------------------------------------------------
def look_at_c2w_gl(eye, target=(0.0, 0.0, 0.0), up=(0.0, 1.0, 0.0)) -> np.ndarray:
    """Blender/NeRF camera-to-world: camera +X right, +Y up, looking down −Z."""
    eye, target, up = (np.asarray(v, dtype=np.float64) for v in (eye, target, up))
    back = eye - target
    back /= np.linalg.norm(back)
    right = np.cross(up, back)
    right /= np.linalg.norm(right)
    cam_up = np.cross(back, right)
    m = np.eye(4)
    m[:3, 0], m[:3, 1], m[:3, 2], m[:3, 3] = right, cam_up, back, eye
    return m


def orbit_eyes(n: int, radius: float = 3.0, height: float = 1.0) -> list[np.ndarray]:
    return [np.array([radius * np.cos(a), height + 0.1 * k, radius * np.sin(a)])
            for k, a in enumerate(np.linspace(0, 2 * np.pi, n, endpoint=False) + 0.3)]


def expected_nerf_pixel(c2w, focal_x, focal_y, cx, cy, point) -> np.ndarray:
    """Independent NeRF projection: camera looks down −Z, image v grows downwards."""
    p = np.linalg.inv(c2w) @ np.append(point, 1.0)
    x, y, z = p[:3]
    return np.array([cx + focal_x * x / -z, cy - focal_y * y / -z])


def colmap_pose(eye, target=(0.0, 0.0, 0.0)) -> tuple[np.ndarray, np.ndarray]:
    """(qvec [w, x, y, z], tvec) of a COLMAP world-to-camera pose looking at ``target``."""
    c2w_cv = look_at_c2w_gl(eye, target) @ np.diag([1.0, -1.0, -1.0, 1.0])
    w2c = np.linalg.inv(c2w_cv)
    x, y, z, w = Rotation.from_matrix(w2c[:3, :3]).as_quat()
    return np.array([w, x, y, z]), w2c[:3, 3].copy()


def expected_colmap_pixel(qvec, tvec, fx, fy, cx, cy, point) -> np.ndarray:
    w, x, y, z = qvec
    p = Rotation.from_quat([x, y, z, w]).apply(point) + tvec
    return np.array([fx * p[0] / p[2] + cx, fy * p[1] / p[2] + cy])


# ---- NeRF-synthetic / instant-ngp -------------------------------------------------------------------------
def make_nerf(root, splits=None, angle_x: float = 0.8, with_ext: bool = False, w: int = W, h: int = H) -> dict:
    """A NeRF-synthetic folder; returns ``{split: [(name, c2w, pixels), ...]}``."""
    root = Path(root)
    splits = splits or {"train": 3, "test": 2}
    out, idx = {}, 0
    for split, n in splits.items():
        frames, out[split] = [], []
        for k, eye in enumerate(orbit_eyes(n, radius=3.0 + 0.2 * len(out))):
            c2w = look_at_c2w_gl(eye)
            px = image_pixels(idx, w, h)
            idx += 1
            write_image(root / split / f"r_{k}.png", px)
            frames.append({"file_path": f"./{split}/r_{k}" + (".png" if with_ext else ""),
                           "rotation": 0.0, "transform_matrix": c2w.tolist()})
            out[split].append((f"{split}/r_{k}", c2w, px))
        (root / f"transforms_{split}.json").write_text(json.dumps({"camera_angle_x": angle_x, "frames": frames},
                                                                  indent=1))
    return out


def make_ngp(root, n: int = 9, intr=None, missing=(), per_frame=None, w: int = W, h: int = H) -> dict:
    """An instant-ngp folder (``transforms.json`` + ``images/``); frames listed in ``missing`` have
    no image file; ``per_frame`` maps a frame index to extra keys. Returns the written data."""
    root = Path(root)
    intr = dict(intr or {"fl_x": 7.0, "fl_y": 6.5, "cx": 4.25, "cy": 2.75, "w": w, "h": h})
    frames, recs = [], []
    for k, eye in enumerate(orbit_eyes(n)):
        c2w = look_at_c2w_gl(eye)
        px = image_pixels(k, w, h, alpha=False)
        if k not in missing:
            write_image(root / "images" / f"{k:04d}.png", px)
        fr = {"file_path": f"images/{k:04d}.png", "sharpness": 50.0, "transform_matrix": c2w.tolist()}
        fr.update((per_frame or {}).get(k, {}))
        frames.append(fr)
        recs.append((f"images/{k:04d}", c2w, px, {**intr, **(per_frame or {}).get(k, {})}))
    data = {**intr, "aabb_scale": 4, "frames": frames}
    (root / "transforms.json").write_text(json.dumps(data, indent=1))
    return {"frames": recs, "json": data}


# ---- COLMAP --------------------------------------------------------------------------------------------
def write_colmap_text(folder, cameras, images, points):
    """``cameras``: [(id, model, w, h, params)]; ``images``: [(id, qvec, tvec, cam_id, name)];
    ``points``: [(id, xyz, rgb uint8, error, track [(image_id, idx)])]."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]"]
    lines += [f"{c[0]} {c[1]} {c[2]} {c[3]} " + " ".join(repr(float(p)) for p in c[4]) for c in cameras]
    (folder / "cameras.txt").write_text("\n".join(lines) + "\n")
    lines = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, "
             "NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)"]
    for k, (iid, q, t, cid, name) in enumerate(images):
        lines.append(f"{iid} " + " ".join(repr(float(v)) for v in (*q, *t)) + f" {cid} {name}")
        lines.append("1.5 2.5 -1 3.0 4.0 1" if k == 0 else "")  # an empty POINTS2D line is legal
    (folder / "images.txt").write_text("\n".join(lines) + "\n")
    lines = ["# 3D point list with one line of data per point:"]
    for pid, xyz, rgb, err, track in points:
        lines.append(f"{pid} " + " ".join(repr(float(v)) for v in xyz) + " " + " ".join(str(int(c)) for c in rgb)
                     + f" {err!r} " + " ".join(f"{a} {b}" for a, b in track))
    (folder / "points3D.txt").write_text("\n".join(lines) + "\n")


def write_colmap_binary(folder, cameras, images, points):
    """COLMAP's binary model format (little-endian), written independently of the reader."""
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    b = bytearray(struct.pack("<Q", len(cameras)))
    for cid, model, w, h, params in cameras:
        b += struct.pack("<iiQQ", cid, MODEL_IDS[model], w, h) + struct.pack(f"<{len(params)}d", *params)
    (folder / "cameras.bin").write_bytes(bytes(b))
    b = bytearray(struct.pack("<Q", len(images)))
    for k, (iid, q, t, cid, name) in enumerate(images):
        b += struct.pack("<i4d3di", iid, *q, *t, cid) + name.encode() + b"\0"
        pts = [(1.5, 2.5, -1), (3.0, 4.0, 1)] if k == 0 else []
        b += struct.pack("<Q", len(pts)) + b"".join(struct.pack("<ddq", *p) for p in pts)
    (folder / "images.bin").write_bytes(bytes(b))
    b = bytearray(struct.pack("<Q", len(points)))
    for pid, xyz, rgb, err, track in points:
        b += struct.pack("<Q3d3Bd", pid, *xyz, *rgb, err) + struct.pack("<Q", len(track))
        b += b"".join(struct.pack("<ii", a, c) for a, c in track)
    (folder / "points3D.bin").write_bytes(bytes(b))


def make_colmap(root, n: int = 9, binary: bool = False, model: str = "PINHOLE", params=None,
                layout: str = "sparse/0", w: int = W, h: int = H, missing=()) -> dict:
    """A COLMAP scene: ``root/images/*.png`` and a model in ``root/<layout>``."""
    root = Path(root)
    params = params or {"PINHOLE": [7.0, 6.5, 4.25, 2.75], "SIMPLE_PINHOLE": [7.0, 4.0, 3.0]}[model]
    cameras = [(1, model, w, h, list(params))]
    images, recs = [], []
    for k, eye in enumerate(orbit_eyes(n)):
        q, t = colmap_pose(eye)
        name = f"img_{k:03d}.png"
        px = image_pixels(k, w, h, alpha=False)
        if k not in missing:
            write_image(root / "images" / name, px)
        images.append((k + 1, q, t, 1, name))
        recs.append((name, q, t, px))
    rng = np.random.default_rng(7)
    points = [(i + 1, rng.normal(size=3), rng.integers(0, 256, 3), 0.5, [(1, 0), (2, 3)]) for i in range(5)]
    folder = root / layout if layout else root
    (write_colmap_binary if binary else write_colmap_text)(folder, cameras, images, points)
    return {"images": recs, "params": params, "points": points, "model_dir": folder}
