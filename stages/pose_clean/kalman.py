"""Constant-velocity Kalman filtering and RTS smoothing of pose channels.

One model for both halves of a pose (paper Sec. 3.3.2, extended):

- translation: the camera centre, 3 channels, state ``[c, c_dot]`` (the paper's 6-state filter);
- rotation: the unit quaternion, 4 channels, state ``[q, q_dot]``; quaternions are aligned to one
  hemisphere first (the paper never does, so a sign flip of the input becomes a huge "jump") and
  the quaternion part of the state is renormalised after every update (paper Eq. 5).

Each channel ``c`` has the same transition (constant velocity, ``order=2``: ``F = [[1, dt],
[0, 1]]``; or constant acceleration, ``order=3``), its own white-noise process variance ``q_c``
(``Q = q_c * Q_discrete_white_noise``) and measurement variance ``r_c``. The 6-state (8-state)
filter is therefore block-diagonal and equals independent per-channel filters; only the
quaternion renormalisation couples the four rotation channels. Two implementations:

- :func:`filterpy_smooth`: filterpy's ``KalmanFilter`` one clip at a time (the reference);
- :func:`batched_smooth`: numpy over a batch of clips at once (what the stage uses; equal to the
  filterpy result to rounding, see the tests).

``q`` and ``r`` come from the data, per clip: ``r`` is the input's own measurement noise, the
robust spread of its high-order differences (:func:`estimate_noise`), so near-exact poses get a
tiny ``r`` and pass nearly unchanged while noisy ones are smoothed; ``q`` by maximising the
filter's innovation likelihood over a grid around a first guess (:func:`fit_process_noise`).
"""

from __future__ import annotations

import math

import numpy as np
from filterpy.common import Q_discrete_white_noise
from filterpy.kalman import KalmanFilter
from scipy.signal import savgol_filter

FIT_WINDOW = 7  # frames of the local quadratic fit that gives the first guess of q
NOISE_DIFF_ORDER = 6  # order of the differences whose spread estimates the measurement noise
MAD_TO_SIGMA = 1.4826  # robust standard deviation of a Gaussian from its median absolute dev.
Q_GRID = np.logspace(-4.0, 4.0, 13)  # multiples of the first q estimate tried by the ML fit


def noise_std(z: np.ndarray, order: int = NOISE_DIFF_ORDER) -> np.ndarray:
    """Robust measurement-noise standard deviation per channel of ``z (..., T, C)``; ``(..., C)``.

    The ``order``-th difference along time is, up to a constant, the residual of a local
    polynomial fit of degree ``order - 1`` over ``order + 1`` frames: it removes smooth motion
    (its response at frequency ``w`` is ``(2 sin(w / 2))^order``, small below a quarter of the
    frame rate) and keeps white noise, whose ``order``-th difference has variance
    ``binom(2 order, order) sigma^2``. Its median absolute value (about 0, robust to the odd
    jump) gives ``sigma``. ``order`` is lowered for short clips; 0 when ``T < 3``.
    """
    z = np.asarray(z, dtype=np.float64)
    t = z.shape[-2]
    order = min(order, t - 2)
    if order < 1:
        return np.zeros((*z.shape[:-2], z.shape[-1]))
    diff = np.diff(z, n=order, axis=-2)  # (..., T - order, C)
    return MAD_TO_SIGMA * np.median(np.abs(diff), axis=-2) / math.sqrt(math.comb(2 * order, order))


def estimate_noise(z: np.ndarray, dt: float, pooled: bool = True) -> tuple[np.ndarray, np.ndarray]:
    """First estimates ``(q (..., C), r (..., C))`` for channels ``z (..., T, C)`` every ``dt`` s.

    ``r``: measurement variance, :func:`noise_std` squared: the input's own noise level, so
    exact or near-exact poses get a tiny ``r`` and are followed closely. ``q``: mean squared
    acceleration of a local quadratic fit over :data:`FIT_WINDOW` frames, a first guess that
    :func:`fit_process_noise` refines. Both are floored to stay positive (relative to the
    channels' spread, so the floor is scale-free) and, with ``pooled``, averaged over channels.
    Leading axes are a batch of clips.
    """
    z = np.asarray(z, dtype=np.float64)
    t, c = z.shape[-2:]
    window = min(FIT_WINDOW, t if t % 2 == 1 else t - 1)
    if window < 5:
        return np.full((*z.shape[:-2], c), 1e-6), np.full((*z.shape[:-2], c), 1e-6)
    r = noise_std(z) ** 2  # (..., C)
    acc = savgol_filter(z, window, 2, deriv=2, axis=-2, mode="interp") / dt**2  # (..., T, C)
    q = np.mean(acc**2, axis=-2)  # (..., C)
    scale = np.var(z, axis=-2) + 1e-12  # (..., C)
    if pooled:  # one value for all channels (isotropic noise: better on short clips)
        q, r, scale = (np.broadcast_to(v.mean(-1, keepdims=True), v.shape) for v in (q, r, scale))
    return np.maximum(q, 1e-12), np.maximum(r, np.maximum(1e-12 * scale, 1e-18))


def motion_model(dt: float, q: float, order: int = 2) -> tuple[np.ndarray, np.ndarray]:
    """``(F (n, n), Q (n, n))`` of one channel: ``order`` 2 is constant velocity (white
    acceleration of variance ``q``), 3 constant acceleration (white jerk)."""
    n = order
    F = np.zeros((n, n))
    for i in range(n):
        for j in range(i, n):
            F[i, j] = dt ** (j - i) / math.factorial(j - i)
    Q = Q_discrete_white_noise(dim=n, dt=dt, var=q)
    return F, Q


def initial_state(
    z: np.ndarray, dt: float, r: np.ndarray, order: int = 2
) -> tuple[np.ndarray, np.ndarray]:
    """``(x0 (..., C, n), P0 (..., C, n, n))`` for ``z (..., T, C)``, ``r (..., C)``.

    Start at the first measurement with variance ``r``; derivatives unknown: their variance is
    ten times the mean squared finite-difference derivative (pooled over channels) plus ``r``'s
    share, so channels with one ``r`` share one ``P0``.
    """
    z = np.asarray(z, dtype=np.float64)
    t, c = z.shape[-2:]
    r = np.broadcast_to(np.asarray(r, dtype=np.float64), (*z.shape[:-2], c))
    x0 = np.zeros((*z.shape[:-2], c, order))
    x0[..., 0] = z[..., 0, :]
    var = np.zeros((*z.shape[:-2], c, order))
    var[..., 0] = r
    for d in range(1, order):
        if t > d:
            spread = np.mean(np.diff(z, n=d, axis=-2) ** 2, axis=(-2, -1))[..., None]  # (..., 1)
        else:
            spread = np.ones((*z.shape[:-2], 1))
        var[..., d] = (10.0 * spread + r) / dt ** (2 * d)
    P0 = var[..., :, None] * np.eye(order)  # (..., C, n, n)
    return x0, P0


def filterpy_smooth(
    z: np.ndarray,
    dt: float,
    q: np.ndarray,
    r: np.ndarray,
    smooth: bool = True,
    normalise: bool = False,
    order: int = 2,
) -> np.ndarray:
    """Filter (and with ``smooth`` RTS-smooth) channels ``z (T, C)`` with filterpy; ``(T, C)``.

    ``q (C,)``, ``r (C,)`` per channel (scalars broadcast). State ``[z_1..z_C, zdot_1..zdot_C,
    ...]`` (``n C``). ``normalise``: the channels are a quaternion; its state part is
    renormalised after every update (paper Eq. 5) and in the output.
    """
    z = np.asarray(z, dtype=np.float64)
    t, c = z.shape
    n = order
    q = np.broadcast_to(np.asarray(q, dtype=np.float64), (c,))
    r = np.broadcast_to(np.asarray(r, dtype=np.float64), (c,))
    F1, Q1 = motion_model(dt, 1.0, n)
    x0, P0 = initial_state(z, dt, r, n)
    eye = np.eye(c)
    kf = KalmanFilter(dim_x=n * c, dim_z=c)
    kf.F = np.kron(F1, eye)  # (nC, nC) positions first, then velocities, ...
    kf.Q = np.kron(Q1, np.diag(q))
    kf.H = np.hstack([eye, np.zeros((c, (n - 1) * c))])  # (C, nC)
    kf.R = np.diag(r)
    kf.x = x0.T.reshape(n * c, 1)
    kf.P = np.zeros((n * c, n * c))
    for d in range(n):
        kf.P[d * c : (d + 1) * c, d * c : (d + 1) * c] = np.diag(P0[:, d, d])
    if not normalise:
        # HAZARDS: batch_filter mis-broadcasts (T, C) measurements; pass (T, C, 1).
        xs, ps, _, _ = kf.batch_filter(z[:, :, None])
    else:
        xs = np.zeros((t, n * c, 1))
        ps = np.zeros((t, n * c, n * c))
        for k in range(t):
            kf.predict()  # as batch_filter: predict, then update, from the first frame on
            kf.update(z[k][:, None])
            kf.x[:c] /= np.linalg.norm(kf.x[:c])
            xs[k], ps[k] = kf.x, kf.P
    if smooth:
        xs, _, _, _ = kf.rts_smoother(xs, ps)
    out = xs[:, :c, 0]  # (T, C)
    if normalise:
        out = out / np.linalg.norm(out, axis=1, keepdims=True)
    return out


def _forward(
    z: np.ndarray, dt: float, q: np.ndarray, r: np.ndarray, normalise: bool, order: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Batched forward filter on ``z (B, T, C)`` with ``q, r (B, C)``.

    Returns ``(xs (T, B, C, n), ps (T, B, C, n, n), loglik (B, C))`` (innovation log-likelihood
    per channel, the first frame left out).
    """
    b, t, c = z.shape
    n = order
    F, Qu = motion_model(dt, 1.0, n)
    x, P = initial_state(z, dt, r, n)  # (B, C, n), (B, C, n, n)
    if np.all(q == q[:, :1]) and np.all(r == r[:, :1]):
        # one q and r per clip: every channel has the same covariance, keep one copy
        q, r, P = q[:, :1], r[:, :1], P[:, :1]
    xs = np.zeros((t, b, c, n))  # filtered states
    ps = np.zeros((t, *P.shape))  # filtered covariances (B, C or 1, n, n)
    loglik = np.zeros((b, c))
    eye = np.eye(n)
    for k in range(t):
        x = x @ F.T  # (B, C, n) predict (also before the first update, as filterpy's batch)
        P = F @ P @ F.T + q[:, :, None, None] * Qu  # (B, C, n, n)
        s = P[..., 0, 0] + r  # (B, C) innovation variance (H picks the position)
        gain = P[..., :, 0] / s[..., None]  # (B, C, n)
        innov = z[:, k, :] - x[..., 0]  # (B, C)
        if k > 0:  # the first innovation only measures the unknown start
            loglik -= 0.5 * (innov**2 / s + np.log(2.0 * np.pi * s))
        x = x + innov[..., None] * gain  # (B, C, n)
        # Joseph form, as filterpy: P = (I - K H) P (I - K H)^T + K r K^T
        ikh = eye - gain[..., :, None] * eye[0]  # (B, C, n, n)
        P = ikh @ P @ np.swapaxes(ikh, -1, -2) + r[..., None, None] * (
            gain[..., :, None] * gain[..., None, :]
        )
        if normalise:
            x[..., 0] /= np.linalg.norm(x[..., 0], axis=1, keepdims=True)
        xs[k], ps[k] = x, P
    return xs, ps, loglik


def _backward(xs: np.ndarray, ps: np.ndarray, dt: float, q: np.ndarray) -> np.ndarray:
    """Rauch-Tung-Striebel pass over filtered ``xs (T, B, C, n)``; smoothed states, same shape."""
    F, Qu = motion_model(dt, 1.0, xs.shape[-1])
    if ps.shape[2] == 1:  # covariance shared by the channels
        q = q[:, :1]
    Q = q[:, :, None, None] * Qu  # (B, C or 1, n, n)
    out = xs.copy()
    xsm, psm = xs[-1], ps[-1]
    for k in range(len(xs) - 2, -1, -1):
        p_pred = F @ ps[k] @ F.T + Q  # (B, C, n, n)
        G = ps[k] @ F.T @ np.linalg.inv(p_pred)  # (B, C, n, n)
        x_pred = xs[k] @ F.T  # (B, C, n)
        xsm = xs[k] + np.einsum(
            "bcij,bcj->bci", np.broadcast_to(G, (*xs.shape[1:], xs.shape[-1])), xsm - x_pred
        )  # (B, C, n)
        psm = ps[k] + G @ (psm - p_pred) @ np.swapaxes(G, -1, -2)
        out[k] = xsm
    return out


def fit_process_noise(
    z: np.ndarray,
    dt: float,
    q0: np.ndarray,
    r: np.ndarray,
    normalise: bool = False,
    order: int = 2,
    grid: np.ndarray = Q_GRID,
) -> np.ndarray:
    """Maximum-likelihood process noise per clip, shared by the clip's channels.

    Tries ``mean_c(q0 (B, C)) * grid`` and keeps the value whose forward filter on
    ``z (B, T, C)`` has the best innovation likelihood summed over channels (one shared value
    fitted better than one per channel on the synthetic trajectories); returns ``(B, C)``.
    """
    z = np.asarray(z, dtype=np.float64)
    b, _, c = z.shape
    g = len(grid)
    cand = np.mean(q0, axis=1)[:, None] * grid[None, :]  # (B, G)
    zz = np.repeat(z, g, axis=0)  # (B*G, T, C)
    rr = np.repeat(np.asarray(r, dtype=np.float64), g, axis=0)  # (B*G, C)
    qq = np.repeat(cand.reshape(b * g, 1), c, axis=1)  # (B*G, C)
    _, _, loglik = _forward(zz, dt, qq, rr, normalise, order)
    best = np.argmax(loglik.sum(axis=1).reshape(b, g), axis=1)  # (B,)
    return np.repeat(cand[np.arange(b), best][:, None], c, axis=1)


def batched_smooth(
    z: np.ndarray,
    dt: float,
    q: np.ndarray,
    r: np.ndarray,
    smooth: bool = True,
    normalise: bool = False,
    order: int = 2,
) -> np.ndarray:
    """The equations of :func:`filterpy_smooth` over a batch: ``z (B, T, C)`` -> ``(B, T, C)``.

    ``q, r (B, C)`` per clip and channel. Channels are independent filters with small ``(n,
    n)`` covariances, so the work is ``O(B T C n^3)`` with tiny matrices, all vectorised.
    """
    z = np.asarray(z, dtype=np.float64)
    b, _, c = z.shape
    q = np.broadcast_to(np.asarray(q, dtype=np.float64), (b, c))
    r = np.broadcast_to(np.asarray(r, dtype=np.float64), (b, c))
    xs, ps, _ = _forward(z, dt, q, r, normalise, order)
    if smooth:
        xs = _backward(xs, ps, dt, q)
    out = np.moveaxis(xs[..., 0], 0, 1)  # (B, T, C)
    if normalise:
        out = out / np.linalg.norm(out, axis=2, keepdims=True)
    return out
