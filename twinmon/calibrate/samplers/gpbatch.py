"""The Karhunen-Loeve + Gaussian-process surrogate's prediction as numpy arithmetic, for the
samplers that move many chains at once.

:class:`GPBatch` evaluates kernel to the training points, times the stored kriging weights,
lifted by the basis, one call for a whole batch of points instead of one OpenTURNS call per
point. It is the same prediction: it checks itself against the OpenTURNS metamodel when built
(agreement ~1e-9 relative; the kriging sum cancels terms ~10^7 times larger than its value,
so neither side is exact to the last bit), and :func:`make_predictor` falls back to
``surrogate.predict`` when it cannot reproduce it. Every row is computed without reference to
the others (element-wise operations, per-row sums, einsum rather than BLAS), so a row's value
does not depend on the batch it is in.

:class:`GPTable` tabulates GPBatch's prediction on a grid over the box and interpolates it
(cubic B-splines): ten times faster, within 1e-6 of GPBatch by its own check (3e-8 on the
pump's surrogate), what :func:`make_predictor` gives the samplers and the forecast.
"""
from __future__ import annotations

import math
from typing import Callable

import numpy as np

from ..shared import worker

#: Rows per block of the batched prediction: its [rows, modes, training points] scratch
#: arrays (a few hundred kB each) stay in the processor's cache.
BLOCK_ROWS = 64
#: Relative agreement with OpenTURNS' prediction required of :class:`GPBatch`.
SELF_CHECK_RTOL = 1e-6
#: :class:`GPTable`: nodes over the box (257 a side for two inputs), at most / at least so
#: many a side, nodes beyond each face, random points of its self-check and the relative
#: agreement with GPBatch's transients it requires: a twentieth of the mean validation
#: error of the surrogates it serves (pump 1.4e-4, water heater 2.8e-4).
TABLE_NODES = 257 ** 2
TABLE_MAX_SIDE = 4097
TABLE_MIN_SIDE = 33
TABLE_PAD = 8
TABLE_CHECK = 4096
TABLE_RTOL = 1e-5


def _matern52(t: np.ndarray, w: np.ndarray, w3: np.ndarray, e: np.ndarray,
              out: np.ndarray) -> np.ndarray:
    """``w (1 + t + t^2/3) exp(-t)`` in place (``w3 = w / 3``); ``e`` is scratch."""
    np.negative(t, out=e)
    np.exp(e, out=e)
    np.multiply(t, w3, out=out)
    out += w
    out *= t
    out += w
    out *= e
    return out


def _matern32(t, w, w3, e, out):
    """``w (1 + t) exp(-t)``."""
    np.negative(t, out=e)
    np.exp(e, out=e)
    np.multiply(t, w, out=out)
    out += w
    out *= e
    return out


def _sq_exp(t, w, w3, e, out):
    """``w exp(-t^2 / 2)``."""
    np.multiply(t, t, out=out)
    out *= -0.5
    np.exp(out, out=out)
    out *= w
    return out


def _abs_exp(t, w, w3, e, out):
    """``w exp(-t)``, t the L1 distance (OpenTURNS' AbsoluteExponential)."""
    np.negative(t, out=out)
    np.exp(out, out=out)
    out *= w
    return out


#: Kernel name -> (factor on the scaled distance, kernel of the scaled distance t, whether t
#: is the L1 distance).
_KERNELS = {"matern52": (math.sqrt(5.0), _matern52, False),
            "matern32": (math.sqrt(3.0), _matern32, False),
            "squared_exponential": (1.0, _sq_exp, False), "exponential": (1.0, _abs_exp, True)}


def _trend_features(U: np.ndarray, trend: str) -> np.ndarray:
    """OpenTURNS' constant / linear / quadratic basis at U [m, d] -> [m, p] (its order:
    1, x_i, then x_i x_j for j = 0..d-1, i <= j)."""
    ones = np.ones((len(U), 1))
    if trend == "constant":
        return ones
    if trend == "linear":
        return np.hstack([ones, U])
    i, j = np.array([(i, j) for j in range(U.shape[1]) for i in range(j + 1)]).T
    return np.hstack([ones, U, U[:, i] * U[:, j]])


class GPBatch:
    """A :class:`~twinmon.reduce.Surrogate`'s ``predict`` as numpy arithmetic.

    Per mode ``k``: ``xi_k(u) = trend_k(u) + sum_i w_ki k_k(u, u_i)`` with ``u`` the input
    scaled to the unit box, ``u_i`` the training points and ``w_k`` OpenTURNS' kriging
    weights (``getCovarianceCoefficients``) times the kernel amplitude squared; the
    transient is ``mean + xi @ basis`` (exponentiated for the log transform).

    Parameters
    ----------
    surrogate : Surrogate

    Raises
    ------
    ValueError
        A kernel or trend it does not know, or a prediction unlike OpenTURNS' (self-check).
    """

    def __init__(self, surrogate):
        s = surrogate
        if s.kernel not in _KERNELS or s.trend not in ("constant", "linear", "quadratic"):
            raise ValueError(f"no batched form of kernel {s.kernel!r} / trend {s.trend!r}")
        self.kernel, self.trend, self.transform = s.kernel, s.trend, s.transform
        self.lo = s.bounds[:, 0].astype(float)
        self.width = (s.bounds[:, 1] - s.bounds[:, 0]).astype(float)
        factor = _KERNELS[s.kernel][0]
        self.inv_scale = factor / np.asarray(s.scales, float)          # [K, d]
        K, (n, d) = s.n_modes, s.X_train.shape
        self.K, self.n, self.d = K, n, d
        self.X_train = np.asarray(s.X_train, float)                     # unit box, [n, d]
        # Scaled training coordinates per input, [K, n] each: a block of rows minus them is
        # one broadcast [rows, K, n] per input.
        self.xs = [s.X_train[None, :, j] * self.inv_scale[:, j, None] for j in range(d)]
        gamma = np.column_stack([np.asarray(r.getCovarianceCoefficients()).ravel()
                                 for r in s._results]).T                # [K, n]
        self.w = np.asarray(s.amplitudes, float)[:, None] ** 2 * gamma             # [K, n]
        self.w3 = self.w / 3.0
        self.trend_matrix = np.array([np.asarray(c, float) for c in s.trend_coefs])  # [K, p]
        self._buffers: dict = {}
        self.mean, self.basis = np.asarray(s.mean, float), np.asarray(s.basis, float)
        self._self_check(s)

    def _self_check(self, s) -> None:
        rng = np.random.default_rng(0)
        X = np.vstack([s.bounds[:, 0] + s.X_train[:8] * self.width,
                       s.bounds[:, 0] + rng.random((8, self.d)) * self.width])
        ref, mine = s.predict(X), self(X)
        err = np.max(np.abs(mine - ref) / np.maximum(np.abs(ref), 1e-300))
        if not err <= SELF_CHECK_RTOL:
            raise ValueError(f"batched prediction differs from OpenTURNS' by {err:.2g}")

    def coefficients(self, X: np.ndarray) -> np.ndarray:
        """Mode coefficients, shape [m, K], for inputs [m, d] (input units)."""
        X = np.atleast_2d(np.asarray(X, float))
        out = np.empty((len(X), self.K))
        for start in range(0, len(X), BLOCK_ROWS):
            out[start:start + BLOCK_ROWS] = self._block(X[start:start + BLOCK_ROWS])
        return out

    def _block(self, X: np.ndarray) -> np.ndarray:
        m, K, n = len(X), self.K, self.n
        U = (X - self.lo) / self.width
        buf = self._buffers.get(m)
        if buf is None:   # scratch reused from call to call (the sampler repeats sizes)
            buf = self._buffers[m] = np.empty((3, m, K, n))
        t, tmp, out = buf
        _, kernel, l1 = _KERNELS[self.kernel]
        # Scaled distance to every training point of every mode: [m, K, n].
        for j in range(self.d):
            uj = U[:, j, None] * self.inv_scale[None, :, j]                     # [m, K]
            dst = t if j == 0 else tmp
            np.subtract(uj[:, :, None], self.xs[j], out=dst)
            if l1:
                np.abs(dst, out=dst)
            else:
                np.multiply(dst, dst, out=dst)
            if j:
                t += tmp
        if not l1:
            np.sqrt(t, out=t)
        xi = kernel(t, self.w, self.w3, tmp, out).sum(axis=2)    # per-row sums, [m, K]
        # einsum's own loops (not BLAS): the same sum order whatever the number of rows
        xi += np.einsum("mp,kp->mk", _trend_features(U, self.trend), self.trend_matrix)
        return xi

    def __call__(self, X: np.ndarray) -> np.ndarray:
        """Predicted transients, shape [m, n_t], for inputs [m, d] (input units)."""
        return self.transient(self.coefficients(X))

    def transient(self, xi: np.ndarray) -> np.ndarray:
        """Transients [m, n_t] from mode coefficients ``xi`` [m, K]."""
        z = np.einsum("mk,kt->mt", xi, self.basis)   # not BLAS, as above
        z += self.mean
        return np.exp(z, out=z) if self.transform == "log" else z


class GPTable:
    """A :class:`GPBatch`'s mode coefficients tabulated on a regular grid over the
    surrogate's box and interpolated by cubic B-splines (``scipy.ndimage``), for the many
    points the samplers and the forecast evaluate: 0.5 µs a point against GPBatch's 4.6,
    transients included (two inputs, 128 training points, 5 modes).

    The table is :data:`TABLE_NODES` nodes over the box (257 a side for two inputs, 40 for
    three), :data:`TABLE_PAD` more beyond each face so that the spline's boundary condition
    stays outside it, and costs one GPBatch evaluation per node when built (0.5 s for two
    inputs, its check included). It is the GP's prediction to well within the surrogate's
    own accuracy: built, it checks itself against GPBatch at :data:`TABLE_CHECK` random
    points of the box and at the training points, and refuses (``ValueError``) a transient
    more than :data:`TABLE_RTOL` off (on the pump's surrogate: 3e-8, against validation
    errors of 1.4e-4 on average; on the water heater's, three inputs, 7e-6 against 2.8e-4,
    1.4 µs a point against GPBatch's 4.4; GPBatch's own rounding moves a transient by
    ~1e-9). A point outside the box (the forecast never sends one; a sampler's proposal
    may) gets GPBatch's. Every row is interpolated on its own: a point's value does not
    depend on the batch it is in.

    Parameters
    ----------
    gp : GPBatch

    Raises
    ------
    ValueError
        Too many inputs for a table worth its nodes (:data:`TABLE_MIN_SIDE`), or a
        prediction unlike GPBatch's (self-check).
    """

    def __init__(self, gp: GPBatch):
        from scipy import ndimage
        d = gp.d
        side = min(TABLE_MAX_SIDE, int(round(TABLE_NODES ** (1.0 / d))))
        if side < TABLE_MIN_SIDE:
            raise ValueError(f"{d} inputs: {side} table nodes a side are too few")
        self.gp, self.d, self.h = gp, d, 1.0 / (side - 1)
        u = np.arange(-TABLE_PAD, side + TABLE_PAD) * self.h
        grids = np.meshgrid(*([u] * d), indexing="ij")
        nodes = np.stack([g.ravel() for g in grids], axis=1)                   # unit box
        xi = gp.coefficients(gp.lo + nodes * gp.width).reshape(grids[0].shape + (gp.K,))
        # The B-spline coefficients interpolating the nodes (prefiltered once).
        self.splines = [ndimage.spline_filter(np.ascontiguousarray(xi[..., k]), order=3,
                                              mode="mirror") for k in range(gp.K)]
        self._self_check()

    def _self_check(self) -> None:
        gp = self.gp
        rng = np.random.default_rng(1)
        U = np.vstack([rng.random((TABLE_CHECK, self.d)), gp.X_train])
        X = gp.lo + U * gp.width
        ref, mine = gp(X), self(X)
        err = np.max(np.abs(mine - ref) / np.maximum(np.abs(ref), 1e-300))
        if not err <= TABLE_RTOL:
            raise ValueError(f"tabulated prediction differs from GPBatch's by {err:.2g}")

    def coefficients(self, X: np.ndarray) -> np.ndarray:
        """Mode coefficients, shape [m, K], for inputs [m, d] (input units)."""
        from scipy import ndimage
        X = np.atleast_2d(np.asarray(X, float))
        U = (X - self.gp.lo) / self.gp.width
        inside = np.all((U >= 0.0) & (U <= 1.0), axis=1)
        out = np.empty((len(X), self.gp.K))
        if not inside.all():
            out[~inside] = self.gp.coefficients(X[~inside])
        if inside.any():
            at = (U[inside] / self.h + TABLE_PAD).T                          # node units
            out[inside] = np.column_stack([
                ndimage.map_coordinates(c, at, order=3, mode="mirror", prefilter=False)
                for c in self.splines])
        return out

    def __call__(self, X: np.ndarray) -> np.ndarray:
        """Predicted transients, shape [m, n_t], for inputs [m, d] (input units)."""
        return self.gp.transient(self.coefficients(X))


def make_predictor(surrogate, table: bool = True
                   ) -> tuple[Callable[[np.ndarray], np.ndarray], bool]:
    """A batch predictor ``X [m, d] -> [m, n_out]`` for the surrogate, and whether it is the
    numpy form (:class:`GPBatch`, tabulated by :class:`GPTable` where that passes its
    self-check, kept per surrogate in the process; ``table=False``: GPBatch itself; a
    stacked view with ``parts`` gets one per part, side by side) or the surrogate's own
    ``predict``."""
    from ...reduce import Surrogate
    parts = getattr(surrogate, "parts", None)
    try:
        if isinstance(surrogate, Surrogate):
            return _numpy_form(surrogate, table), True
        if parts and all(isinstance(p, Surrogate) for p in parts.values()):
            gps = [_numpy_form(p, table) for p in parts.values()]
            return (lambda X: np.hstack([g(X) for g in gps])), True
    except ValueError:
        pass
    return surrogate.predict, False


#: Tables built in this process, by surrogate fingerprint (a fleet's calibrate or forecast
#: builds one per worker; a process calibrating again, as backtest does, reuses it), the last
#: ``TABLES_KEPT`` (about 3 MB each for two inputs).
_TABLES: dict = {}
TABLES_KEPT = 4


def _numpy_form(surrogate, table: bool):
    """GPBatch of one surrogate, tabulated when asked and it passes its self-check (a
    surrogate seen before in this process: its form kept, GPBatch not built and checked
    against OpenTURNS again)."""
    if not table:
        return GPBatch(surrogate)
    key = surrogate.fingerprint()
    if key not in _TABLES:
        gp = GPBatch(surrogate)
        while len(_TABLES) >= TABLES_KEPT:
            _TABLES.pop(next(iter(_TABLES)))
        try:
            _TABLES[key] = GPTable(gp)
        except ValueError:
            _TABLES[key] = gp
    return _TABLES[key]


def worker_predict() -> Callable[[np.ndarray], np.ndarray]:
    """The batch predictor of a worker process's surrogate
    (:func:`~twinmon.calibrate.shared.init_worker`), made on its first batch and kept."""
    if "predict" not in worker:
        worker["predict"] = make_predictor(worker["surrogate"])[0]
    return worker["predict"]
