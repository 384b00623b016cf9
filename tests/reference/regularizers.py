"""Reference (array-of-rows) forms of the mesh regularisers' energies and gradients: the implementation of
``triplet_cl.regularizers`` before its column-wise rewrite (session 62), kept to check that rewrite bit for bit
(``tests/test_regularizers.py``). Pure numpy, no tape."""

from __future__ import annotations

import numpy as np

from triplet_cl.activations import normalize, normalize_bwd


def _scatter_rows(num_rows: int, index: np.ndarray, values: np.ndarray) -> np.ndarray:
    out = np.zeros((num_rows, values.shape[1]), dtype=values.dtype)
    np.add.at(out, index, values)
    return out


def face_normal_consistency(v: np.ndarray, faces: np.ndarray, pairs: np.ndarray, scale: float, kappa, eps: float,
                            v_out: float = 1.0):
    """``(energy, gradient [N, 3])`` of ``Σ_pairs ρ(1 − n_a·n_b) · scale`` (``ρ`` as FaceNormalConsistency)."""
    faces = np.asarray(faces, np.int64)
    tri = v[faces]
    e1, e2 = tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]
    c = np.cross(e1, e2)
    n = normalize(c, eps)
    a, b = pairs[:, 0], pairs[:, 1]
    x = 1.0 - np.sum(n[a] * n[b], axis=1)
    k = kappa
    if k is not None:
        energy = np.asarray(np.sum(k * np.log1p(x / k) + x**5 / 5) * scale)
    else:
        energy = np.asarray(np.sum(x) * scale)
    s = -float(v_out) * scale
    if k is not None:
        s = (s * (1.0 / (1.0 + x / k) + x**4))[:, None]
    v_n = _scatter_rows(len(faces), np.concatenate([a, b]), np.concatenate([s * n[b], s * n[a]]))
    v_c = normalize_bwd(c, v_n, eps)
    v_e1, v_e2 = np.cross(e2, v_c), np.cross(v_c, e1)
    corner = np.stack([-(v_e1 + v_e2), v_e1, v_e2], axis=1)
    return energy, _scatter_rows(len(v), faces.reshape(-1), corner.reshape(-1, 3))


def material_gtv(x: np.ndarray, edges: np.ndarray, sqrt_w: np.ndarray, scale: float, v_out: float = 1.0):
    """``(energy, gradient [N, C])`` of ``Σ sqrt_w · |x_i − x_j|₁ · scale`` over ``edges`` (both directions in
    ``sqrt_w``, as MaterialGTV)."""
    diff = x[edges[:, 0]] - x[edges[:, 1]]
    energy = np.asarray(np.sum(sqrt_w * np.abs(diff)) * scale)
    g = sqrt_w * np.sign(diff) * (float(v_out) * scale)
    return energy, _scatter_rows(len(x), np.concatenate([edges[:, 0], edges[:, 1]]), np.concatenate([g, -g]))
