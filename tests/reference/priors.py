"""Loop references of the priors (triplet_cl/priors.py): plain per-pair / per-light Python, energies only."""

from __future__ import annotations

import math

import numpy as np


def sig(x):
    return 1.0 / (1.0 + math.exp(-x))


def knn_pairs(points, k):
    pts = np.asarray(points, float)
    n = len(pts)
    out = set()
    for i in range(n):
        d = [(float(np.sum((pts[i] - pts[j]) ** 2)), j) for j in range(n) if j != i]
        for _, j in sorted(d)[:k]:
            out.add((min(i, j), max(i, j)))
    return sorted(out)


def knn_smoothness(raw, faces, pairs, cols, eps):
    m = [[sum(sig(raw[v, c]) for v in f) / 3.0 for c in cols] for f in faces]
    tot = 0.0
    for a, b in pairs:
        for c in range(len(cols)):
            d = m[a][c] - m[b][c]
            tot += math.sqrt(d * d + eps * eps) - eps
    return tot / (len(pairs) * len(cols))


def metallic_l1(raw, col):
    return sum(sig(x) for x in raw[:, col]) / len(raw)


def roughness_target(raw, col, r0):
    return sum((sig(x) - r0) ** 2 for x in raw[:, col]) / len(raw)


def ambient_fraction(ambient_colors, points, directionals, center):
    """ambient_colors: [rgb]; points: [(position, rgb intensity)] with falloff; directionals: [rgb]."""
    a = sum(sum(c) / 3.0 for c in ambient_colors)
    p = 0.0
    for q, i in points:
        p += (sum(i) / 3.0) / max(sum((q[k] - center[k]) ** 2 for k in range(3)), 1e-6)
    p += sum(sum(i) / 3.0 for i in directionals)
    a = abs(a)
    den = math.pi * a + p
    return 0.0 if den <= 0 else math.pi * a / den


def chroma(colors, delta):
    tot = 0.0
    for c in colors:
        m = sum(c) / 3.0
        tot += sum((x - m) ** 2 for x in c) / (m * m + delta)
    return tot
