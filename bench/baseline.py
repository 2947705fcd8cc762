#!/usr/bin/env python3
"""Baseline for the benchmarks: the two-step distributed filter of docs/theory.md §2, §4 written the way a
numpy/FilterPy user would, one subsystem at a time in a Python loop.

Usage: baseline.py CONFIG MEASUREMENTS INPUTS OUT

Reads a sisfilt config (no overrides, unknown dropouts), the measurement and input CSVs, and
writes the estimates CSV of docs/theory.md §13 (x̂(t|t), upper triangle of P(t|t)). Default options of
sisfilt: banded step-1 solve (here a dense solve of the link equations with numpy), local
second moment, step 1 fed by the filtered estimates, Joseph-form covariance update.
"""
import sys
import tomllib

import numpy as np


def main():
    config, meas_path, inputs_path, out_path = sys.argv[1:5]
    with open(config, "rb") as f:
        cfg = tomllib.load(f)
    mdl = cfg["model"]
    A, B, D, G, J, M = (np.array(mdl[k], dtype=float) for k in "ABDGJM")
    n, q, N = A.shape[0], J.shape[0], cfg["subsystems"]
    m = len(mdl["C"][0]) if "C" in mdl else 0
    C = np.array(mdl.get("C", np.zeros((n, m))), dtype=float).reshape(n, m)
    H = np.array(mdl.get("H", np.zeros((D.shape[0], m))), dtype=float).reshape(D.shape[0], m)
    R = np.array(mdl.get("R", np.zeros((q, m))), dtype=float).reshape(q, m)
    Q = np.array(mdl.get("Q", np.zeros((n, n))), dtype=float)
    pp, pm = cfg["interconnection"]["plus"], cfg["interconnection"]["minus"]
    s = pp + pm
    p = cfg["dropout"]["p"]
    p = np.full(N, p) if np.isscalar(p) else np.array(p)
    m0 = np.array(cfg["initial"].get("mean", np.zeros(n)), dtype=float)
    P0 = np.array(cfg["initial"]["cov"], dtype=float)

    y = np.loadtxt(meas_path, delimiter=",", skiprows=1, ndmin=2)
    u = np.loadtxt(inputs_path, delimiter=",", skiprows=1, ndmin=2) if m > 0 else None
    T = y.shape[0] // N
    y = y[:, 2:].reshape(T, N, q)
    u = u[:, 2:].reshape(T, N, m) if m > 0 else np.zeros((T, N, 0))

    # The link equations of docs/theory.md §2 as one dense matrix (factorised once: G is constant).
    G11, G12, G21, G22 = G[:pp, :pp], G[:pp, pp:], G[pp:, :pp], G[pp:, pp:]
    L = N - 1
    K = np.eye(L * s)
    for i in range(L):
        a, b = i * s, i * s + pp
        if i > 0:
            K[a:a + pp, a - s:a - s + pp] -= G11
        K[a:a + pp, b:b + pm] -= G12
        K[b:b + pm, a:a + pp] -= G21
        if i + 1 < L:
            K[b:b + pm, b + s:b + s + pm] -= G22
    Kinv = np.linalg.inv(K) if L > 0 else np.zeros((0, 0))

    xp = [m0.copy() for _ in range(N)]
    Tp = [P0.copy() for _ in range(N)]
    mean = [m0.copy() for _ in range(N)]
    Px = [P0.copy() for _ in range(N)]
    iu = np.triu_indices(n)
    out = open(out_path, "w")
    cols = [f"x{k + 1}" for k in range(n)] + [f"P{r + 1}_{c + 1}" for r, c in zip(*iu)]
    out.write("t,i," + ",".join(cols) + "\n")
    for t in range(T):
        xf, Pf = [None] * N, [None] * N
        for i in range(N):
            S = Px[i] + np.outer(mean[i], mean[i])
            Hm = p[i] * J
            Reff = M + p[i] * (1 - p[i]) * J @ S @ J.T
            Sig = Hm @ Tp[i] @ Hm.T + Reff
            W = np.linalg.solve(Sig, Hm @ Tp[i])
            Lg = W.T
            xf[i] = xp[i] + Lg @ (y[t, i] - R @ u[t, i] - Hm @ xp[i])
            F = np.eye(n) - Lg @ Hm
            Pf[i] = F @ Tp[i] @ F.T + Lg @ Reff @ Lg.T
            Pf[i] = 0.5 * (Pf[i] + Pf[i].T)
            out.write(f"{t + 1},{i + 1}," + ",".join(repr(float(v)) for v in np.concatenate([xf[i], Pf[i][iu]])) + "\n")
        z = np.concatenate([D @ xf[i] + H @ u[t, i] for i in range(N)])
        rhs = np.zeros(L * s)
        for i in range(L):
            rhs[i * s:i * s + pp] = z[i * s:i * s + pp]
            rhs[i * s + pp:(i + 1) * s] = z[(i + 1) * s + pp:(i + 2) * s]
        sol = Kinv @ rhs
        v = np.zeros((N, s))
        for i in range(L):
            v[i + 1, :pp] = sol[i * s:i * s + pp]
            v[i, pp:] = sol[i * s + pp:(i + 1) * s]
        for i in range(N):
            xp[i] = A @ xf[i] + B @ v[i] + C @ u[t, i]
            Tp[i] = A @ Pf[i] @ A.T + Q
            Tp[i] = 0.5 * (Tp[i] + Tp[i].T)
            mean[i] = A @ mean[i] + B @ v[i] + C @ u[t, i]
            Px[i] = A @ Px[i] @ A.T + Q
    out.close()


if __name__ == "__main__":
    main()
