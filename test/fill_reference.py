"""Plain per-cell Fill-Terrain (paper 000, Fig. 6): the oracle for terrain_perception.fill.

Written for clarity, not speed: Python loops over cells, samples and window entries, one
library patch at a time. It follows the fill order and the random-number draw order documented
in ``terrain_perception/fill.py`` so that both give the same map for the same seed, but it
shares no code with it.
"""

import math

import numpy as np


def fill_terrain_reference(heights, upper_bound, library, w, n, sigma_cells, seed,
                           constrained=True, return_feasible=False):
    """Returns (filled heights (nx, ny) float64, chosen global library position per cell)
    and, with ``return_feasible``, a mask of the cells where some drawn patch had v_k = 0."""
    H = np.array(heights, dtype=np.float64)
    nx, ny = H.shape
    if upper_bound is None or not constrained:
        ub = np.full(H.shape, np.inf)
    else:
        ub = np.where(np.isnan(upper_bound), np.inf, np.asarray(upper_bound, np.float64))
    r = w // 2
    known = np.isfinite(H)
    rng = np.random.default_rng(seed)
    rank = rng.permutation(nx * ny).reshape(nx, ny)
    W = np.empty((w, w))
    for a in range(w):
        for b in range(w):
            da, db = (a - r) / sigma_cells, (b - r) / sigma_cells
            W[a, b] = math.exp(-0.5 * (da * da + db * db))
    lib = [np.asarray(t, np.float64) for t in library]
    counts = [(t.shape[0] - w + 1) * (t.shape[1] - w + 1) for t in lib]
    total = sum(counts)

    def patch(g):
        for t, c in zip(lib, counts):
            if g < c:
                i, j = divmod(g, t.shape[1] - w + 1)
                return t[i:i + w, j:j + w]
            g -= c
        raise AssertionError('position out of range')

    # known cells in each cell's w x w window (cells outside the grid are unknown)
    count = np.zeros((nx, ny), np.int64)
    for x in range(nx):
        for y in range(ny):
            for a in range(max(0, x - r), min(nx, x + r + 1)):
                for b in range(max(0, y - r), min(ny, y + r + 1)):
                    count[x, y] += known[a, b]
    choice = np.full((nx, ny), -1, np.int64)
    feasible_mask = np.zeros((nx, ny), bool)
    while not known.all():
        cand = [(x, y) for x in range(nx) for y in range(ny) if not known[x, y] and count[x, y]]
        key = {c: count[c] * nx * ny + rank[c] for c in cand}
        selected = []
        for (x, y) in cand:
            best = True
            for a in range(max(0, x - r), min(nx, x + r + 1)):
                for b in range(max(0, y - r), min(ny, y + r + 1)):
                    if (a, b) != (x, y) and (a, b) in key and key[(a, b)] > key[(x, y)]:
                        best = False
            if best:
                selected.append((x, y))
        selected.sort(key=lambda c: c[0] * ny + c[1])
        for (x, y) in selected:
            A = np.zeros((w, w))
            B = np.zeros((w, w))
            Abar = np.full((w, w), np.inf)
            for a in range(w):
                for b in range(w):
                    xa, yb = x - r + a, y - r + b
                    if 0 <= xa < nx and 0 <= yb < ny:
                        Abar[a, b] = ub[xa, yb]
                        if known[xa, yb]:
                            A[a, b] = H[xa, yb]
                            B[a, b] = 1.0
            m = B.sum()
            u = rng.random(n)
            hs, ss, vs, gs = [], [], [], []
            for k in range(n):
                g = min(int(u[k] * total), total - 1)
                C = patch(g)
                bias = (B * (A - C)).sum() / m
                hs.append(C[r, r] + bias)
                ss.append((W * B * (C - A + bias) ** 2).sum())
                vs.append((np.maximum(C + bias - Abar, 0.0) ** 2).sum())
                gs.append(g)
            feasible = [k for k in range(n) if vs[k] == 0.0]
            feasible_mask[x, y] = bool(feasible)
            if feasible:
                kbest = min(feasible, key=lambda k: ss[k])
            else:
                kbest = min(range(n), key=lambda k: vs[k])
            H[x, y] = hs[kbest]
            choice[x, y] = gs[kbest]
            known[x, y] = True
            for a in range(max(0, x - r), min(nx, x + r + 1)):
                for b in range(max(0, y - r), min(ny, y + r + 1)):
                    count[a, b] += 1
    if return_feasible:
        return H, choice, feasible_mask
    return H, choice
