"""numba kernels of the iLQR backward pass (box-DDP Riccati sweep, projected-Newton box QP).

Kept apart from :mod:`npp_ros.trajopt.ilqr` so that importing a plant does not load numba; the
optimizer imports this module when it is built.
"""

from __future__ import annotations

import math

import numpy as np
from numba import njit

from npp_ros.policy.dataset import FloatArray


@njit(cache=True)
def _cholesky(h: FloatArray) -> tuple[FloatArray, bool]:
    n = h.shape[0]
    lower = np.zeros((n, n))
    for i in range(n):
        for j in range(i + 1):
            acc = h[i, j]
            for p in range(j):
                acc -= lower[i, p] * lower[j, p]
            if i == j:
                if not acc > 0.0:
                    return lower, False
                lower[i, i] = math.sqrt(acc)
            else:
                lower[i, j] = acc / lower[j, j]
    return lower, True


@njit(cache=True)
def _cholesky_solve(lower: FloatArray, rhs: FloatArray) -> FloatArray:
    """Solve (L L') X = rhs column by column; rhs is (n, k)."""
    n, cols = rhs.shape
    out = np.empty((n, cols))
    for c in range(cols):
        y = np.empty(n)
        for i in range(n):
            acc = rhs[i, c]
            for p in range(i):
                acc -= lower[i, p] * y[p]
            y[i] = acc / lower[i, i]
        for i in range(n - 1, -1, -1):
            acc = y[i]
            for p in range(i + 1, n):
                acc -= lower[p, i] * out[p, c]
            out[i, c] = acc / lower[i, i]
    return out


@njit(cache=True)
def _quadratic(h: FloatArray, g: FloatArray, x: FloatArray) -> float:
    return 0.5 * x @ (h @ x) + g @ x


@njit(cache=True)
def _box_qp(
    h: FloatArray, g: FloatArray, lo: FloatArray, hi: FloatArray, x0: FloatArray
) -> tuple[FloatArray, np.ndarray]:
    """min 0.5 x'hx + g'x on lo <= x <= hi by projected Newton (h positive definite).

    Returns the minimiser and its free set (coordinates not held at a bound by the gradient).
    With no finite bound this is one Newton step.
    """
    m = g.shape[0]
    x = np.minimum(np.maximum(x0, lo), hi)
    free = np.ones(m, dtype=np.bool_)
    for _ in range(100):
        grad = h @ x + g
        nfree = 0
        for i in range(m):
            held = (x[i] <= lo[i] and grad[i] > 0.0) or (x[i] >= hi[i] and grad[i] < 0.0)
            free[i] = not held
            nfree += 0 if held else 1
        if nfree == 0:
            break
        idx = np.nonzero(free)[0]
        sub = np.empty((nfree, nfree))
        rhs = np.empty((nfree, 1))
        gnorm = 0.0
        for a in range(nfree):
            rhs[a, 0] = -grad[idx[a]]
            gnorm = max(gnorm, abs(grad[idx[a]]))
            for b in range(nfree):
                sub[a, b] = h[idx[a], idx[b]]
        if gnorm < 1e-13:
            break
        lower, _ = _cholesky(sub)
        step = _cholesky_solve(lower, rhs)
        direction = np.zeros(m)
        for a in range(nfree):
            direction[idx[a]] = step[a, 0]
        f0 = _quadratic(h, g, x)
        alpha = 1.0
        moved = False
        while alpha > 1e-12:
            trial = np.minimum(np.maximum(x + alpha * direction, lo), hi)
            if _quadratic(h, g, trial) - f0 <= 0.1 * (grad @ (trial - x)):
                moved = True
                break
            alpha *= 0.5
        if not moved:
            break
        shift = np.max(np.abs(trial - x))
        x = trial
        if shift < 1e-14:
            break
    grad = h @ x + g
    for i in range(m):
        free[i] = not ((x[i] <= lo[i] and grad[i] > 0.0) or (x[i] >= hi[i] and grad[i] < 0.0))
    return x, free


@njit(cache=True)
def backward_pass(
    a: FloatArray,
    b: FloatArray,
    sx: FloatArray,
    sxx: FloatArray,
    cu: FloatArray,
    cuu: FloatArray,
    actions: FloatArray,
    lo: FloatArray,
    hi: FloatArray,
    mu: float,
    k_prev: FloatArray,
) -> tuple[FloatArray, FloatArray, FloatArray, float, float, int]:
    """Riccati sweep of box-DDP with Gauss-Newton dynamics (iLQR) and Quu + mu I.

    sx, sxx are the state cost's derivatives at x_0 .. x_T. Returns feedforward k (T, m),
    gains K (T, m, n), W_x (T, n) = gradient of the cost-to-go from x_t (the post-step costs
    of steps t .. T-1), the expected decrease terms, and -1 or the step where Quu + mu I was
    not positive definite.
    """
    horizon, n, m = b.shape[0], b.shape[1], b.shape[2]
    k = np.zeros((horizon, m))
    gains = np.zeros((horizon, m, n))
    wx = np.zeros((horizon, n))
    vx = sx[horizon].copy()
    vxx = sxx[horizon].copy()
    dv1 = 0.0
    dv2 = 0.0
    eye = np.eye(m)
    for t in range(horizon - 1, -1, -1):
        at = a[t]
        bt = b[t]
        qx = at.T @ vx
        qu = cu[t] + bt.T @ vx
        va = vxx @ at
        vb = vxx @ bt
        qxx = at.T @ va
        quu = cuu[t] + bt.T @ vb
        qux = bt.T @ va
        quu_reg = quu + mu * eye
        _, ok = _cholesky(quu_reg)
        if not ok:
            return k, gains, wx, dv1, dv2, t
        kt, free = _box_qp(quu_reg, qu, lo - actions[t], hi - actions[t], k_prev[t])
        nfree = 0
        for i in range(m):
            nfree += 1 if free[i] else 0
        kt_gain = np.zeros((m, n))
        if nfree > 0:
            idx = np.nonzero(free)[0]
            sub = np.empty((nfree, nfree))
            rhs = np.empty((nfree, n))
            for p in range(nfree):
                for q in range(nfree):
                    sub[p, q] = quu_reg[idx[p], idx[q]]
                for q in range(n):
                    rhs[p, q] = -qux[idx[p], q]
            sub_lower, _ = _cholesky(sub)
            sol = _cholesky_solve(sub_lower, rhs)
            for p in range(nfree):
                for q in range(n):
                    kt_gain[idx[p], q] = sol[p, q]
        k[t] = kt
        gains[t] = kt_gain
        quu_k = quu @ kt
        dv1 += kt @ qu
        dv2 += 0.5 * (kt @ quu_k)
        w = qx + kt_gain.T @ quu_k + kt_gain.T @ qu + qux.T @ kt
        wxx = qxx + kt_gain.T @ (quu @ kt_gain) + kt_gain.T @ qux + qux.T @ kt_gain
        wxx = 0.5 * (wxx + wxx.T)
        wx[t] = w
        vx = w + sx[t]
        vxx = wxx + sxx[t]
    return k, gains, wx, dv1, dv2, -1


def compile_kernels() -> None:
    """Compile (or load from numba's cache) the backward pass, so no request pays for it."""
    n, m = 2, 1
    backward_pass(
        np.zeros((1, n, n)),
        np.zeros((1, n, m)),
        np.zeros((2, n)),
        np.zeros((2, n, n)),
        np.zeros((1, m)),
        np.ones((1, m, m)),
        np.zeros((1, m)),
        np.full(m, -1.0),
        np.full(m, 1.0),
        0.0,
        np.zeros((1, m)),
    )
