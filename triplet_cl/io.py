"""Writing results: atomic files, RGBA PNGs (straight alpha), JSON, the triplet soup as PLY."""

from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path

import numpy as np


def strict_json_object(pairs: list) -> dict:
    """``json.loads(..., object_pairs_hook=strict_json_object)``: a key given twice in one object is a ValueError
    (``json`` keeps the last silently: a transforms file with two ``camera_angle_x`` trained on one of them)."""
    out = {}
    for k, v in pairs:
        if k in out:
            raise ValueError(f"the key {k!r} appears twice in one object")
        out[k] = v
    return out


def atomic_write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` through a temporary file and a rename: never a half-written file."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.name}.", suffix=".tmp", dir=path.parent)
    try:
        with os.fdopen(fd, "wb") as f:
            f.write(data)
            f.flush()
            os.fsync(f.fileno())
        os.chmod(tmp, 0o666 & ~_umask())  # mkstemp makes 0600; give the file the usual permissions
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def _umask() -> int:
    mask = os.umask(0)
    os.umask(mask)
    return mask


def write_json(path, obj) -> None:
    """Atomic JSON write (indented, numpy scalars/arrays converted)."""

    def conv(o):
        if isinstance(o, np.ndarray):
            return o.tolist()
        if isinstance(o, np.generic):
            return o.item()
        if isinstance(o, Path):
            return str(o)
        raise TypeError(f"not JSON serialisable: {type(o).__name__}")

    atomic_write_bytes(path, (json.dumps(obj, indent=2, default=conv) + "\n").encode())


def write_png(path, rgb: np.ndarray, alpha: np.ndarray | None = None) -> None:
    """Write an 8-bit PNG (RGB, or RGBA with **straight** alpha) atomically through OpenImageIO.

    Args:
        rgb: ``[H, W, 3]`` float in [0, 1] (clipped). alpha: optional ``[H, W]`` in [0, 1].
    """
    import OpenImageIO as oiio

    rgb = np.clip(np.asarray(rgb, np.float32), 0, 1)
    img = rgb if alpha is None else np.concatenate([rgb, np.clip(np.asarray(alpha, np.float32), 0, 1)[..., None]], -1)
    h, w, c = img.shape
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=".png", dir=path.parent)
    try:  # from the file's creation on (a signal in between left it behind)
        os.close(fd)
        out = oiio.ImageOutput.create(tmp)
        if out is None:
            raise OSError(f"OpenImageIO cannot write PNG files: {oiio.geterror()}")
        spec = oiio.ImageSpec(w, h, c, oiio.UINT8)
        spec.attribute("oiio:UnassociatedAlpha", 1)  # the colour is not premultiplied by alpha
        if not out.open(tmp, spec):
            raise OSError(f"cannot write {path}: {out.geterror()}")
        ok = out.write_image(np.ascontiguousarray((img * 255.0 + 0.5).astype(np.uint8)))
        out.close()
        if not ok:
            raise OSError(f"cannot write {path}: {out.geterror()}")
        os.chmod(tmp, 0o666 & ~_umask())
        os.replace(tmp, path)
    except BaseException:
        Path(tmp).unlink(missing_ok=True)
        raise


def write_soup_ply(path, V: np.ndarray, F: np.ndarray, attributes: dict[str, np.ndarray],
                   comment: str = "triplet_cl triangle soup", albedo_space: str = "srgb") -> None:
    """Binary PLY of a triangle soup with per-vertex float attributes (``name -> [N] or [N, k]``;
    ``[N, k]`` becomes ``name_0 .. name_{k-1}``, ``albedo`` [N,3] becomes ``red/green/blue`` bytes too).

    The float attributes are written as given. The ``red/green/blue`` bytes are display colours, which
    viewers (MeshLab, Blender, Open3D) take as sRGB-encoded: ``albedo_space="linear"`` (a run of the linear
    colour pipeline) encodes the albedo with the sRGB transfer function for them; ``"srgb"`` (already
    encoded values) writes it unchanged. The header says which."""
    if albedo_space not in ("srgb", "linear"):
        raise ValueError(f"albedo_space must be 'srgb' or 'linear', got {albedo_space!r}")
    V = np.asarray(V, np.float32)
    n = len(V)
    cols = [("x", V[:, 0]), ("y", V[:, 1]), ("z", V[:, 2])]
    for name, a in attributes.items():
        a = np.asarray(a, np.float32).reshape(n, -1)
        if a.shape[1] == 1:
            cols.append((name, a[:, 0]))
        else:
            cols += [(f"{name}_{i}", a[:, i]) for i in range(a.shape[1])]
    dtype = [(name, "<f4") for name, _ in cols]
    rgb = attributes.get("albedo")
    if rgb is not None:
        dtype += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
    verts = np.empty(n, dtype=dtype)
    for name, a in cols:
        verts[name] = a
    if rgb is not None:
        rgb = np.clip(np.asarray(rgb, np.float32), 0, 1)
        if albedo_space == "linear":
            from .ops.color import srgb_encode

            rgb = np.clip(srgb_encode(rgb), 0, 1).astype(np.float32)
        c = (rgb * 255 + 0.5).astype(np.uint8)
        verts["red"], verts["green"], verts["blue"] = c[:, 0], c[:, 1], c[:, 2]
    F = np.asarray(F, np.int32)
    faces = np.empty(len(F), dtype=[("n", "u1"), ("idx", "<i4", (3,))])
    faces["n"] = 3
    faces["idx"] = F
    props = "".join(
        f"property {'float' if t == '<f4' else 'uchar'} {name}\n" for name, t in dtype
    )
    note = ""
    if rgb is not None:
        note = ("comment red/green/blue: the linear albedo sRGB-encoded (the float albedo_* are linear)\n"
                if albedo_space == "linear" else "comment red/green/blue: the albedo as stored (sRGB-encoded)\n")
    header = (f"ply\nformat binary_little_endian 1.0\ncomment {comment}\n{note}element vertex {n}\n{props}"
              f"element face {len(F)}\nproperty list uchar int vertex_indices\nend_header\n")
    atomic_write_bytes(path, header.encode() + verts.tobytes() + faces.tobytes())
