"""Derives the Winograd transforms of `deepstereo-core/src/conv/winograd/algos.rs` and
measures their f32 rounding error (the figures quoted in `winograd/mod.rs`).

F(m, r) by Toom-Cook on the points given plus infinity (alpha = m + r - 1 = 6): with `E_n`
the alpha x n evaluation matrix (rows [1, a, .., a^(n-1)], and [0, .., 0, 1] for infinity)
and `V = E_alpha`, linear convolution is `s = V^-1 [(E_r g) * (E_m h)]`; its transpose is
the correlation `y = E_m^T [(E_r g) * (V^-T d)]`, so `A^T = E_m^T`, `G = E_r`,
`B^T = V^-T`. Exact fractions; then f32 on random data against an f64 direct sum.

    .venv/bin/python python/winograd_transforms.py
"""

from fractions import Fraction as F

import numpy as np


def evaluation(points, n):
    rows = [[F(p) ** i for i in range(n)] for p in points]
    return rows + [[F(0)] * (n - 1) + [F(1)]]


def inverse(m):
    n = len(m)
    a = [row[:] + [F(int(i == j)) for j in range(n)] for i, row in enumerate(m)]
    for c in range(n):
        p = next(i for i in range(c, n) if a[i][c] != 0)
        a[c], a[p] = a[p], a[c]
        a[c] = [v / a[c][c] for v in a[c]]
        for i in range(n):
            if i != c and a[i][c] != 0:
                f = a[i][c]
                a[i] = [vi - f * vc for vi, vc in zip(a[i], a[c])]
    return [row[n:] for row in a]


def transforms(points, m, r):
    alpha = len(points) + 1
    assert alpha == m + r - 1
    v_inv = inverse(evaluation(points, alpha))
    bt = [[v_inv[j][i] for j in range(alpha)] for i in range(alpha)]
    g = evaluation(points, r)
    em = evaluation(points, m)
    at = [[em[j][i] for j in range(alpha)] for i in range(m)]
    return bt, g, at


def f32_error(points, m, r, cin=64, trials=20, seed=0):
    """Largest |winograd - exact| and |direct f32 sum - exact| over the sum of the
    products' magnitudes (inputs in [0, 1), weights N(0, 0.05), cin channels), over random
    2D tiles."""
    bt, g, at = [np.array(x, dtype=np.float64).astype(np.float32) for x in transforms(points, m, r)]
    rng = np.random.default_rng(seed)
    alpha = m + r - 1
    worst, direct = 0.0, 0.0
    for _ in range(trials):
        d = rng.random((cin, alpha, alpha)).astype(np.float32)
        w = (rng.standard_normal((cin, r, r)) * 0.05).astype(np.float32)
        exact = np.array([[np.sum(d[:, i:i + r, j:j + r].astype(np.float64) * w) for j in range(m)] for i in range(m)])
        u = np.einsum("ij,cjk,lk->cil", g, w, g).astype(np.float32)
        v = np.einsum("ij,cjk,lk->cil", bt, d, bt).astype(np.float32)
        y = at @ np.sum(u * v, axis=0, dtype=np.float32) @ at.T
        mag = np.sum(np.abs(d[:, :r, :r].astype(np.float64) * w))
        worst = max(worst, float(np.abs(y - exact).max() / mag))
        # The direct sum in f32, term by term (as the direct kernels accumulate).
        for i in range(m):
            for j in range(m):
                acc = np.float32(0)
                for t in (d[:, i:i + r, j:j + r] * w).ravel():
                    acc = np.float32(acc + t)
                direct = max(direct, float(abs(acc - exact[i, j]) / mag))
    return worst, direct


def main():
    for name, m, r, points in [
        ("F(2x2, 5x5)", 2, 5, [0, 1, -1, F(1, 2), F(-1, 2)]),
        ("F(4x4, 3x3)", 4, 3, [0, 1, -1, F(1, 2), -2]),
        ("F(4x4, 3x3), points 0, +-1, +-2", 4, 3, [0, 1, -1, 2, -2]),
    ]:
        bt, g, at = transforms(points, m, r)
        wino, direct = f32_error(points, m, r)
        print(f"{name}: f32 error {wino:.2e} of the products' magnitude (direct f32 sum {direct:.2e})")
        for label, mat in [("B^T", bt), ("G", g), ("A^T", at)]:
            print(f"  {label}:")
            for row in mat:
                print("    [" + ", ".join(str(v) for v in row) + "]")


if __name__ == "__main__":
    main()
