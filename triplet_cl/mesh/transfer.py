"""Nearest-neighbour attribute transfer from the triplet soup to the vertices of a new mesh.

Donors are the soup's *face points*: every soup vertex (its own value) and every face centroid
(the mean of its corners' values). A donor carries the opacity of its face (the mean activated
alpha of its corners); donors of faces below ``min_alpha`` never donate (transparent junk faces
left over from training would otherwise paint the mesh), unless no face reaches it (then every
face donates). Each destination vertex takes the ``k`` nearest donors (``scipy.spatial.cKDTree``)
and blends them with weights ``w_i = α_i / (d_i + ε)`` (``ε`` = 1e-3 × the donor spread, so an
exact hit dominates without a division by zero); ``k = 1`` is the plain nearest opaque donor.

Values are blended linearly as given: raw parameters (logits of material and alpha, vertex-SH rows;
a blend of logits stays a valid logit) or activated attributes (a blend of values in [0, 1] stays
in [0, 1]).
"""

from __future__ import annotations

import numpy as np
from scipy.spatial import cKDTree

from ..ops.common import check_faces, check_real

__all__ = ["face_points", "transfer_attributes"]


def face_points(V: np.ndarray, F: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Donor points of a soup: ``(P [N + M, 3], owner [N + M] int64)`` — the vertices then the face
    centroids; ``owner`` is the face of each donor (a vertex used by several faces: the first)."""
    V = np.asarray(V, np.float64)
    F = np.asarray(F, np.int64)
    owner_v = np.full(len(V), -1, np.int64)
    owner_v[F[::-1].reshape(-1)] = np.repeat(np.arange(len(F))[::-1], 3)  # first face wins
    P = np.concatenate([V, V[F].mean(axis=1)]) if len(F) else V
    return P, np.concatenate([owner_v, np.arange(len(F))])


def transfer_attributes(src_V, src_F, src_values: dict, dst_V, k: int = 4, src_alpha=None,
                        min_alpha: float = 0.1) -> dict:
    """Blend per-vertex soup values onto new vertices by their nearest opaque donors.

    Args:
        src_V: ``[N, 3]`` soup vertices; src_F: ``[M, 3]`` soup faces (M ≥ 1).
        src_values: ``name -> [N, ...]`` per-vertex values (any trailing shape, e.g. material
            ``[N, Cm]``, alpha ``[N, 1]``, vertex SH ``[N, 6, B]``).
        dst_V: ``[P, 3]`` vertices that receive values.
        k: donors per destination vertex (≥ 1).
        src_alpha: ``[N]`` or ``[N, 1]`` *activated* soup opacity in [0, 1]; None treats every face
            as opaque.
        min_alpha: faces whose mean alpha is below it do not donate (unless none reaches it).

    Returns:
        ``name -> [P, ...]`` arrays (float64, the trailing shape of each input).
    """
    V = check_real("src_V", src_V, (None, 3), np.float64)
    F = check_faces("src_F", src_F, len(V))
    D = check_real("dst_V", dst_V, (None, 3), np.float64)
    if len(F) == 0:
        raise ValueError("src_F must hold at least one face to transfer attributes from, got 0 faces")
    if not (isinstance(k, int | np.integer) and k >= 1):
        raise ValueError(f"k must be an integer >= 1, got {k!r}")
    n = len(V)
    vals = {}
    for name, a in src_values.items():
        a = np.asarray(a)
        if a.ndim < 1 or a.shape[0] != n:
            raise ValueError(f"src_values[{name!r}] must have {n} rows (one per soup vertex), "
                             f"got shape {list(a.shape)}")
        vals[name] = check_real(f"src_values[{name!r}]", a, a.shape, np.float64)
    if src_alpha is None:
        face_a = np.ones(len(F))
    else:
        al = np.asarray(src_alpha, np.float64).reshape(-1)
        if al.shape != (n,):
            raise ValueError(f"src_alpha must have {n} values (one per soup vertex), "
                             f"got shape {list(np.shape(src_alpha))}")
        if not (np.isfinite(al).all() and al.min() >= 0 and al.max() <= 1):
            raise ValueError("src_alpha must be activated opacity in [0, 1] (pass sigmoid(raw alpha))")
        face_a = al[F].mean(axis=1)
    P, owner = face_points(V, F)
    used = owner >= 0  # vertices used by no face never donate
    donor_ok = used & (face_a[np.maximum(owner, 0)] >= min_alpha)
    if not donor_ok.any():
        donor_ok = used
    idx = np.flatnonzero(donor_ok)
    w_alpha = np.maximum(face_a[owner[idx]], 1e-6)
    kk = int(min(k, len(idx)))
    tree = cKDTree(P[idx])
    if len(D) == 0:
        return {name: np.zeros((0,) + a.shape[1:]) for name, a in vals.items()}
    d, j = tree.query(D, k=kk)
    d, j = d.reshape(len(D), kk), j.reshape(len(D), kk)
    eps = 1e-3 * float(np.ptp(P[idx], axis=0).max() or 1.0)
    w = w_alpha[j] / (d + eps)
    w /= w.sum(axis=1, keepdims=True)
    out = {}
    for name, a in vals.items():
        donors = np.concatenate([a, a[F].mean(axis=1)])[idx]  # [D, ...] vertex values then centroid means
        flat = donors.reshape(len(idx), -1)
        out[name] = np.einsum("pk,pkc->pc", w, flat[j]).reshape((len(D),) + a.shape[1:])
    return out
