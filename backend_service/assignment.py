"""Optimal one-to-one assignment for the association: the Hungarian method (exact, in numpy, so the
backend needs no scipy) and the gated assignment of detections to robots with the least total
``cost² / 2``.
"""

from __future__ import annotations

import math

import numpy as np


def hungarian(cost: np.ndarray) -> list[tuple[int, int]]:
    """Minimum-cost assignment of a finite (n, m) cost matrix: ``min(n, m)`` (row, column)
    pairs, each row and column at most once, least total cost (the Hungarian method with
    potentials, O(n² m) for n <= m; the matrix is transposed otherwise). Exact."""
    c = np.asarray(cost, dtype=np.float64)
    if c.ndim != 2:
        raise ValueError(f"hungarian: expected a 2-D cost matrix, got shape {c.shape}")
    if c.size == 0:
        return []
    if not np.all(np.isfinite(c)):
        raise ValueError("hungarian: costs must be finite (gate with a large finite cost)")
    if c.shape[0] > c.shape[1]:
        return [(i, j) for j, i in hungarian(c.T)]
    n, m = c.shape
    rows = c.tolist()
    inf = math.inf
    u = [0.0] * (n + 1)
    v = [0.0] * (m + 1)
    match = [0] * (m + 1)  # column j (1-based) -> row (1-based), 0 = free
    way = [0] * (m + 1)
    for i in range(1, n + 1):
        match[0] = i
        j0 = 0
        minv = [inf] * (m + 1)
        used = [False] * (m + 1)
        while True:
            used[j0] = True
            i0 = match[j0]
            row = rows[i0 - 1]
            ui0 = u[i0]
            delta = inf
            j1 = 0
            for j in range(1, m + 1):
                if not used[j]:
                    cur = row[j - 1] - ui0 - v[j]
                    if cur < minv[j]:
                        minv[j] = cur
                        way[j] = j0
                    if minv[j] < delta:
                        delta = minv[j]
                        j1 = j
            for j in range(m + 1):
                if used[j]:
                    u[match[j]] += delta
                    v[j] -= delta
                else:
                    minv[j] -= delta
            j0 = j1
            if match[j0] == 0:
                break
        while j0:
            j1 = way[j0]
            match[j0] = match[j1]
            j0 = j1
    return [(match[j] - 1, j - 1) for j in range(1, m + 1) if match[j]]


def gated_assignment(costs: np.ndarray, gate: float) -> tuple[list[tuple[int, int]], float]:
    """The gated optimal assignment of ``costs`` (D, R): pairs costing at most ``gate`` only,
    as many pairs as possible, then the least total ``cost² / 2``. Returns the pairs and that
    total plus ``big`` for each row left unassigned (comparable between calls on the same
    shape)."""
    d, r = costs.shape
    nll = 0.5 * np.square(costs)
    big = (0.5 * gate * gate + 1.0) * (min(d, r) + 1)
    finite = np.where(costs <= gate, nll, big)
    pairs = [(i, j) for i, j in hungarian(finite) if costs[i, j] <= gate]
    total = sum(float(nll[i, j]) for i, j in pairs) + big * (d - len(pairs))
    return pairs, total
