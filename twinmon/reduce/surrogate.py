"""The surrogate: Karhunen-Loeve modes of the transients, one Gaussian process per mode
(OpenTURNS), its fit on the training runs and its validation on the held-out test runs."""
from __future__ import annotations

import json
from contextlib import contextmanager
from dataclasses import dataclass, field

import numpy as np

from ..config import ReduceConfig
from ..errors import CalibrationError, ConfigError


# ---------------------------------------------------------------------------------------
# OpenTURNS building blocks
# ---------------------------------------------------------------------------------------
def _kernel(name: str, dim: int, scale=None, amplitude=None):
    import openturns as ot
    scale = [0.3] * dim if scale is None else list(map(float, scale))
    amplitude = [1.0] if amplitude is None else list(map(float, amplitude))
    if name == "matern52":
        return ot.MaternModel(scale, amplitude, 2.5)
    if name == "matern32":
        return ot.MaternModel(scale, amplitude, 1.5)
    if name == "squared_exponential":
        return ot.SquaredExponential(scale, amplitude)
    if name == "exponential":
        return ot.AbsoluteExponential(scale, amplitude)
    raise ValueError(f"unknown kernel {name!r}")


def _basis(name: str, dim: int):
    import openturns as ot
    factory = {"constant": ot.ConstantBasisFactory, "linear": ot.LinearBasisFactory,
               "quadratic": ot.QuadraticBasisFactory}[name]
    return factory(dim).build()


def _regression(Xu: np.ndarray, y: np.ndarray, kernel: str, trend: str, scale, amplitude,
                coefficients):
    """Conditioned Gaussian process from stored hyperparameters (same path after a reload)."""
    import openturns as ot
    dim = Xu.shape[1]
    basis = _basis(trend, dim)
    funcs = [basis.build(i) for i in range(basis.getSize())]
    trend_fn = ot.LinearCombinationFunction(funcs, list(map(float, coefficients)))
    algo = ot.GaussianProcessRegression(ot.Sample(Xu), ot.Sample(y[:, None]),
                                        _kernel(kernel, dim, scale, amplitude), trend_fn)
    algo.run()
    return algo.getResult()


# ---------------------------------------------------------------------------------------
# The surrogate
# ---------------------------------------------------------------------------------------
@dataclass
class Surrogate:
    """Reduced model: inputs [n, d] (input units) -> output transients [n, n_t].

    Attributes
    ----------
    input_names : list of str
    bounds : ndarray, shape [d, 2]
        Training box (low, high) per input; predictions outside it are extrapolations.
    time : ndarray, shape [n_t], s
    mean : ndarray, shape [n_t]
        Mean training transient (output units, or their log with ``transform="log"``).
    basis : ndarray, shape [K, n_t]
        Lifting of the K mode coefficients: ``z = mean + xi @ basis``; the prediction is
        ``y = exp(z)`` with ``transform="log"``, else ``y = z``.
    eigenvalues : ndarray, shape [m]
        All Karhunen-Loeve eigenvalues (for the variance ratio).
    truncation_var : ndarray, shape [n_t]
        Variance of the training transients not captured by the K kept modes.
    X_train : ndarray, shape [n, d]
        Training inputs scaled to the unit box.
    xi_train : ndarray, shape [n, K]
        Mode coefficients of the training transients.
    kernel, trend : str
    scales : ndarray, shape [K, d]; amplitudes : ndarray, shape [K]; trend_coefs : list of arrays
        Hyperparameters of each mode's Gaussian process.
    """

    input_names: list[str]
    bounds: np.ndarray
    time: np.ndarray
    mean: np.ndarray
    basis: np.ndarray
    eigenvalues: np.ndarray
    truncation_var: np.ndarray
    X_train: np.ndarray
    xi_train: np.ndarray
    kernel: str
    trend: str
    scales: np.ndarray
    amplitudes: np.ndarray
    trend_coefs: list[np.ndarray]
    transform: str = "log"
    units: str = "1"
    #: Held-out FMU runs the surrogate was validated on: inputs [m, d] (input units) and
    #: transients [m, n_t] (output units); kept so later stages can measure the surrogate's
    #: error on what they compute from it (the health indicator).
    X_test: np.ndarray = field(default_factory=lambda: np.empty((0, 0)))
    Y_test: np.ndarray = field(default_factory=lambda: np.empty((0, 0)))
    #: Hash of what the surrogate predicts from (see :meth:`fingerprint`); set on reading.
    content_id: str = ""
    #: Further channels whose surrogates the same file holds (see
    #: :func:`read_channel_surrogates`); set on reading.
    channel_names: list = field(default_factory=list)
    _results: list = field(default_factory=list, repr=False)
    _meta = None
    _covs: list = field(default_factory=list, repr=False)

    def __post_init__(self):
        if not self._results:
            self._results = [
                _regression(self.X_train, self.xi_train[:, k], self.kernel, self.trend,
                            self.scales[k], [self.amplitudes[k]], self.trend_coefs[k])
                for k in range(self.n_modes)]
        import openturns as ot
        self._meta = ot.AggregatedFunction([r.getMetaModel() for r in self._results])
        self._covs = [ot.GaussianProcessConditionalCovariance(r) for r in self._results]

    @property
    def n_modes(self) -> int:
        return self.basis.shape[0]

    @property
    def variance_ratio(self) -> float:
        return float(self.eigenvalues[:self.n_modes].sum() / self.eigenvalues.sum())

    def scale(self, X: np.ndarray) -> np.ndarray:
        """Inputs [n, d] (input units) -> unit box."""
        lo, hi = self.bounds[:, 0], self.bounds[:, 1]
        return (np.atleast_2d(X) - lo) / (hi - lo)

    def in_box(self, X: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """True per row [n] when the point lies in the training box."""
        u = self.scale(X)
        return np.all((u >= -tol) & (u <= 1 + tol), axis=1)

    def coefficients(self, X: np.ndarray) -> np.ndarray:
        """Predicted mode coefficients, shape [n, K]."""
        return np.array(self._meta(self.scale(X)))

    def _untransform(self, z: np.ndarray) -> np.ndarray:
        return np.exp(z) if self.transform == "log" else z

    def fingerprint(self) -> str:
        """SHA-256 of the arrays and settings the predictions depend on. Two surrogates with
        the same fingerprint predict the same, whatever file (and creation time) holds them;
        calibrate records it so forecast can tell whether a posterior belongs to a surrogate."""
        import hashlib
        h = hashlib.sha256(f"{self.kernel}|{self.trend}|{self.transform}|"
                           f"{json.dumps(list(self.input_names))}".encode())
        for a in (self.bounds, self.time, self.mean, self.basis, self.truncation_var,
                  self.X_train, self.xi_train, self.scales, self.amplitudes, *self.trend_coefs):
            h.update(np.ascontiguousarray(a, dtype=float).tobytes())
        return h.hexdigest()

    def training_outputs(self) -> np.ndarray:
        """The training transients as the kept modes reproduce them, shape [n, n_t], output
        units (for range checks; the truncated modes hold a tiny share of the variance)."""
        return self._untransform(self.mean + self.xi_train @ self.basis)

    def predict(self, X: np.ndarray) -> np.ndarray:
        """Predicted transients, shape [n, n_t], output units."""
        return self._untransform(self.mean + self.coefficients(X) @ self.basis)

    def predict_with_var(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Prediction and its variance per time step, both shape [n, n_t].

        The variance is the modes' kriging variances lifted by the basis (the modes are
        independent) plus the truncation variance, mapped to output units by the delta
        method (``var_y = y^2 var_z`` for the log transform)."""
        import openturns as ot
        y = self.predict(X)
        Xu = ot.Sample(self.scale(X))
        var = np.column_stack([np.asarray(c.getConditionalMarginalVariance(Xu)).ravel()
                               for c in self._covs])
        var_z = np.maximum(var, 0.0) @ (self.basis ** 2) + self.truncation_var
        return y, (y ** 2 * var_z if self.transform == "log" else var_z)

    def predict_var(self, X: np.ndarray) -> np.ndarray:
        """Predictive variance per time step, shape [n, n_t], (output units)^2."""
        return self.predict_with_var(X)[1]


def resolve_transform(Y: np.ndarray, transform: str) -> str:
    """``log`` or ``none`` for ``auto``: log when every value is > 0 and the values span
    less than four decades (a transient resting near 0 would be learnt in log scale where
    its noise, not its shape, dominates)."""
    if transform != "auto":
        return transform
    Y = np.asarray(Y, float)
    if Y.size and np.all(Y > 0) and Y.max() / Y.min() <= 1e4:
        return "log"
    return "none"


def fit_surrogate(X: np.ndarray, Y: np.ndarray, time: np.ndarray, bounds: np.ndarray,
                  input_names: list[str], rc: ReduceConfig, units: str = "1") -> Surrogate:
    """Fit the Karhunen-Loeve + Gaussian-process surrogate.

    Parameters
    ----------
    X : ndarray, shape [n, d]
        Training inputs (input units).
    Y : ndarray, shape [n, n_t]
        Training transients (output units), no NaN.
    time : ndarray, shape [n_t]
    bounds : ndarray, shape [d, 2]
    input_names : list of str
    rc : ReduceConfig
    """
    import openturns as ot
    n, n_t = Y.shape
    if n_t < 2:
        raise CalibrationError(f"the output has {n_t} sample per run; a transient needs at "
                               "least 2 (model.output.times)")
    transform = resolve_transform(Y, rc.transform)
    if transform == "log":
        if np.any(Y <= 0):
            i, j = np.argwhere(Y <= 0)[0]
            raise ConfigError(f"reduce.transform: log needs positive outputs, but run {i} "
                              f"has {Y[i, j]:g} at t = {time[j]:g} s; set reduce.transform: "
                              "none (or auto)")
        Y = np.log(Y)
    mean = Y.mean(axis=0)
    Yc = Y - mean
    mesh = ot.RegularGrid(float(time[0]), float(time[1] - time[0]), n_t) if n_t > 1 \
        else ot.Mesh(ot.Sample([[float(time[0])]]))
    ps = ot.ProcessSample(mesh, 0, 1)
    for row in Yc:
        ps.add(ot.Sample(row[:, None]))
    kl = ot.KarhunenLoeveSVDAlgorithm(ps, 0.0, True)
    kl.run()
    res = kl.getResult()
    eig = np.array(res.getEigenvalues())
    eig = np.maximum(eig, 0.0)
    ratio = np.cumsum(eig) / eig.sum()
    K = int(min(np.searchsorted(ratio, rc.variance_threshold - 1e-15) + 1, rc.max_modes,
                len(eig)))
    xi_all = np.array(res.project(ps))              # [n, m]
    # The lifting of OpenTURNS' coefficients: least squares recovers it exactly for the kept
    # modes and lets the prediction be a plain matrix product.
    basis = np.linalg.lstsq(xi_all[:, :K], Yc, rcond=None)[0]   # [K, n_t]
    resid = Yc - xi_all[:, :K] @ basis
    truncation_var = (resid ** 2).mean(axis=0)

    lo, hi = bounds[:, 0], bounds[:, 1]
    Xu = (X - lo) / (hi - lo)
    d = X.shape[1]
    scales, amps, coefs = np.zeros((K, d)), np.zeros(K), []
    stopped = []
    for k in range(K):
        y = xi_all[:, k]
        fitter = ot.GaussianProcessFitter(ot.Sample(Xu), ot.Sample(y[:, None]),
                                          _kernel(rc.kernel, d), _basis(rc.trend, d))
        # Scales on the unit box: from a fifth of a grid cell to ten box widths.
        fitter.setOptimizationBounds(ot.Interval([1e-2] * d, [10.0] * d))
        with ot_log_captured() as log:
            fitter.run()
        if any("Cobyla" in line for line in log):
            stopped.append(k + 1)
        r = fitter.getResult()
        cov = r.getCovarianceModel()
        scales[k] = np.array(cov.getScale())
        amps[k] = float(cov.getAmplitude()[0])
        coefs.append(np.array(r.getTrendCoefficients()).ravel())
    s = Surrogate(input_names=list(input_names), bounds=np.asarray(bounds, float),
                  time=np.asarray(time, float), mean=mean, basis=basis, eigenvalues=eig,
                  truncation_var=truncation_var, X_train=Xu, xi_train=xi_all[:, :K],
                  kernel=rc.kernel, trend=rc.trend, scales=scales, amplitudes=amps,
                  trend_coefs=coefs, transform=transform, units=units)
    #: The modes (1-based) whose hyperparameter search stopped at its evaluation limit (not
    #: stored: reduce says so once, as a warning).
    s.optimiser_stopped = stopped
    return s


@contextmanager
def ot_log_captured():
    """OpenTURNS' log lines written inside the block, as a list of str filled when it ends,
    instead of on stderr: there they came with terminal colour codes into pipes and logs,
    whatever ``-q`` said, and without the mode or channel they concern."""
    import os
    import tempfile

    import openturns as ot
    fd, path = tempfile.mkstemp(prefix="twinmon-otlog-", suffix=".txt")
    os.close(fd)
    lines: list[str] = []
    ot.Log.SetFile(path)
    try:
        yield lines
    finally:
        ot.Log.Flush()
        ot.Log.SetFile("")            # back to stderr
        try:
            with open(path, errors="replace") as f:
                lines += [ln.strip() for ln in f if ln.strip()]
        finally:
            os.unlink(path)


@dataclass
class Validation:
    """Surrogate against held-out FMU runs.

    ``max_range_error``/``mean_range_error``: |pred - fmu| over all test runs and steps, as a
    fraction of the output's range over the test runs (the output's own scale; meaningful for
    any output). ``max_rel_error``/``mean_rel_error``: |pred - fmu| / |fmu|, only where the
    output stays away from 0 (every |fmu| above 1 % of that range), else NaN. ``q2``: per
    mode, 1 - SSE/SST of the coefficients; ``coverage_90``: fraction of test values inside
    the surrogate's 90 % predictive band.
    """

    max_range_error: float
    mean_range_error: float
    max_rel_error: float
    mean_rel_error: float
    q2: list[float]
    coverage_90: float
    n_test: int
    output_range: float = float("nan")

    def as_dict(self) -> dict:
        return {"max_range_error": self.max_range_error,
                "mean_range_error": self.mean_range_error,
                "max_rel_error": self.max_rel_error, "mean_rel_error": self.mean_rel_error,
                "output_range": self.output_range,
                "q2": self.q2, "coverage_90": self.coverage_90, "n_test": self.n_test}


def validate_surrogate(s: Surrogate, X: np.ndarray, Y: np.ndarray) -> Validation:
    """Relative error per time step, Q2 per mode and band coverage on test runs."""
    nan = float("nan")
    if len(X) == 0:
        return Validation(nan, nan, nan, nan, [], nan, 0)
    pred, var = s.predict_with_var(X)
    err = np.abs(pred - Y)
    span = float(Y.max() - Y.min())
    scale = span if span > 0 else float(np.abs(Y).max()) or 1.0
    away = bool(np.all(np.abs(Y) > 0.01 * scale))
    rel = err / np.abs(Y) if away else np.full_like(err, np.nan)
    Z = np.log(Y) if s.transform == "log" else Y
    xi_true = (Z - s.mean) @ np.linalg.pinv(s.basis)
    xi_pred = s.coefficients(X)
    q2 = [float(1 - np.sum((xi_pred[:, k] - xi_true[:, k]) ** 2)
                / np.sum((xi_true[:, k] - xi_true[:, k].mean()) ** 2)) for k in range(s.n_modes)]
    cover = float(np.mean(np.abs(pred - Y) <= 1.6449 * np.sqrt(var)))
    return Validation(float(err.max() / scale), float(err.mean() / scale), float(rel.max()),
                      float(rel.mean()), q2, cover, len(X), span)
