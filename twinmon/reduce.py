"""Stage ``reduce``: a cheap surrogate of the FMU (Karhunen-Loeve + Gaussian processes).

The simulated transients ``Y`` [n, n_t] are centred (OpenTURNS' SVD algorithm does not centre
them itself), decomposed by OpenTURNS' Karhunen-Loeve SVD algorithm, and the fewest modes
whose variance ratio reaches the config's threshold are kept. Each mode's coefficient is
learnt by one anisotropic Gaussian process (``GaussianProcessFitter`` for the hyperparameters,
``GaussianProcessRegression`` for the conditioning) over the inputs scaled to the unit box.
Predictions are lifted back to the time steps; the predictive variance of each mode and the
variance of the discarded modes are propagated to each time step.

A surrogate is rebuilt from the arrays stored in ``surrogate.h5`` (no pickles): the regression
is always built from the stored hyperparameters and trend coefficients, both right after the
fit and after a reload, so a reloaded surrogate predicts exactly what the fitted one did.

Further channels the design recorded (``model.channels``, e.g. a speed or a current) get a
surrogate each, by the same algorithm with transform ``auto`` (``reduce.channels`` chooses
which), stored under ``/channels/<FMU variable>`` with the root's layout; ``calibrate`` puts
the observed ones in its likelihood. :func:`read_surrogate` loads the output's only,
:func:`read_channel_surrogates` the channels'. A file written before channels existed simply
has none.
"""
from __future__ import annotations

import dataclasses
import json
import os
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from . import artifacts
from .config import Config, ReduceConfig
from .errors import ArtifactError, CalibrationError
from .simulate import read_simulations

#: Config sections recorded in the artifact (and compared by ``twinmon run``).
SECTIONS = ("model", "reduce")


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
            raise CalibrationError(f"run {i} has output {Y[i, j]:g} <= 0 at t = {time[j]:g} s: "
                                   "the log transform needs positive outputs "
                                   "(set reduce.transform: none)")
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
    for k in range(K):
        y = xi_all[:, k]
        fitter = ot.GaussianProcessFitter(ot.Sample(Xu), ot.Sample(y[:, None]),
                                          _kernel(rc.kernel, d), _basis(rc.trend, d))
        # Scales on the unit box: from a fifth of a grid cell to ten box widths.
        fitter.setOptimizationBounds(ot.Interval([1e-2] * d, [10.0] * d))
        fitter.run()
        r = fitter.getResult()
        cov = r.getCovarianceModel()
        scales[k] = np.array(cov.getScale())
        amps[k] = float(cov.getAmplitude()[0])
        coefs.append(np.array(r.getTrendCoefficients()).ravel())
    return Surrogate(input_names=list(input_names), bounds=np.asarray(bounds, float),
                     time=np.asarray(time, float), mean=mean, basis=basis, eigenvalues=eig,
                     truncation_var=truncation_var, X_train=Xu, xi_train=xi_all[:, :K],
                     kernel=rc.kernel, trend=rc.trend, scales=scales, amplitudes=amps,
                     trend_coefs=coefs, transform=transform, units=units)


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


# ---------------------------------------------------------------------------------------
# Stage entry point and artifact
# ---------------------------------------------------------------------------------------
@dataclass
class ReduceSummary:
    """What :func:`reduce` did; ``as_dict`` is the ``--json`` output.

    ``channels`` maps each further channel that got a surrogate to its modes, variance
    ratio and test validation (``as_dict`` form)."""

    modes: int
    variance_ratio: float
    validation: Validation
    train_runs: int
    output: str
    channels: dict = field(default_factory=dict)
    warnings: list = field(default_factory=list)

    def as_dict(self) -> dict:
        return {"modes": self.modes, "variance_ratio": self.variance_ratio,
                "test": self.validation.as_dict(), "train_runs": self.train_runs,
                "output": self.output, "channels": self.channels,
                "warnings": list(self.warnings)}


@artifacts.locks_output("output", "twinmon reduce")
def reduce(cfg: Config, simulations: str | os.PathLike, output: str | os.PathLike) -> ReduceSummary:
    """Fit the surrogate on the training runs, validate it on the test runs, write it.

    The output's surrogate comes first; then one per further channel of
    :func:`channels_to_reduce` (same training and test runs)."""
    sims = read_simulations(simulations)
    check_made_for(cfg, simulations, sims.input_names, sims.time, sims.bounds, "simulate")
    ok = sims.ok["train"]
    if ok.sum() < 2 * len(sims.input_names) + 2:
        raise CalibrationError(f"{simulations}: only {int(ok.sum())} successful training runs")
    okt = sims.ok["test"]

    def fit(Y: np.ndarray, Y_test: np.ndarray, rc: ReduceConfig, units: str, what: str):
        try:
            s = fit_surrogate(sims.X["train"][ok], Y, sims.time, sims.bounds,
                              sims.input_names, rc, units)
        except CalibrationError as exc:
            raise CalibrationError(f"{simulations}: {what}{exc.message}") from None
        s.X_test, s.Y_test = sims.X["test"][okt], Y_test
        return s, validate_surrogate(s, s.X_test, s.Y_test)

    s, val = fit(sims.Y["train"][ok], sims.Y["test"][okt], cfg.reduce,
                 cfg.model.output.units, "")
    names, warnings = channels_to_reduce(cfg, sims)
    capped = cap_warning(s, cfg.reduce, val.max_range_error,
                         f"the output {cfg.model.output.name}")
    warnings = [capped] * bool(capped) + warnings
    # Each channel its own transform: a speed or a current may cross zero where the output
    # (learnt in log scale) does not.
    rc = dataclasses.replace(cfg.reduce, transform="auto")
    fitted = {}
    for ch in names:
        Y = sims.channels["train"][ch][ok]
        if np.ptp(Y, axis=0).max() <= 1e-12 * max(float(np.abs(Y).max()), 1e-300):
            warnings.append(f"channel {ch} does not change over the design box: it says "
                            "nothing about the inputs; no surrogate")
            continue
        fitted[ch] = fit(Y, sims.channels["test"][ch][okt], rc,
                         cfg.model.variable_words(ch)[1], f"channel {ch}: ")
        capped = cap_warning(fitted[ch][0], rc, fitted[ch][1].max_range_error,
                             f"channel {ch}")
        if capped:
            warnings.append(capped)
    write_surrogate(output, s, val, cfg, [simulations], channels=fitted)
    return ReduceSummary(s.n_modes, s.variance_ratio, val, int(ok.sum()), str(output),
                         {ch: {"modes": c.n_modes, "variance_ratio": c.variance_ratio,
                               "transform": c.transform, "test": v.as_dict()}
                          for ch, (c, v) in fitted.items()}, warnings)


def cap_warning(s: "Surrogate", rc: ReduceConfig, max_range_error: float | None = None,
                what: str = "the output") -> str:
    """A warning when a cap, not ``reduce.variance_threshold``, decided the surrogate's modes
    ("" when the threshold was reached).

    The caps: ``reduce.max_modes``, and the number of training runs (Karhunen-Loeve gives
    at most one mode per run, so ``simulate.train_size`` bounds the modes too).

    Parameters
    ----------
    s : Surrogate
    rc : ReduceConfig
        The settings it was fitted with.
    max_range_error : float, optional
        Its largest test error, fraction of the output's range (said in the warning).
    what : str
        Which surrogate, for the message.
    """
    ratio = s.variance_ratio
    if ratio >= rc.variance_threshold - 1e-15:
        return ""
    if s.n_modes >= rc.max_modes:
        key, why = "reduce.max_modes", f"reduce.max_modes = {rc.max_modes}"
    elif s.n_modes >= len(s.eigenvalues):
        key, why = "simulate.train_size", f"the {len(s.eigenvalues)} training runs"
    else:
        return ""
    err = (f"; its test error reaches {100 * max_range_error:.3g} % of the range"
           if max_range_error is not None and np.isfinite(max_range_error) else "")
    return (f"surrogate of {what}: capped by {why} at {s.n_modes} modes, "
            f"{100 * ratio:.4g} % of the variance, short of reduce.variance_threshold "
            f"{rc.variance_threshold:g}{err}; raise {key} for a closer surrogate")


def channels_to_reduce(cfg: Config, sims) -> tuple[list[str], list[str]]:
    """The further channels that get a surrogate, and warnings about the others.

    ``reduce.channels`` when set (each must be in the design), else every channel of
    ``model.channels`` the design recorded (a design simulated before channels were recorded
    has none: a warning says so).

    Raises
    ------
    ArtifactError
        ``reduce.channels`` names a channel the design did not record.
    """
    recorded = set(sims.channels.get("train", {}))
    wanted = cfg.reduce.channels
    if wanted is not None:
        for ch in wanted:
            if ch not in recorded:
                raise ArtifactError(f"{sims.path}: the design did not record channel {ch!r} "
                                    "(reduce.channels); re-run simulate")
        return list(wanted), []
    missing = [ch for ch in cfg.model.channels if ch not in recorded]
    warnings = [f"the design did not record channel(s) {', '.join(missing)}: no surrogate; "
                "re-run simulate to learn them"] if missing else []
    return [ch for ch in cfg.model.channels if ch in recorded], warnings


def check_made_for(cfg: Config, path, input_names, time, bounds, rerun: str) -> None:
    """An artifact (simulations or surrogate) must come from this config's inputs, design box
    and time grid; else one line naming what differs and the stage(s) to re-run.

    Parameters
    ----------
    input_names : list of str
    time : ndarray, shape [n_t], s
    bounds : ndarray, shape [d, 2]
    rerun : str
        What to re-run, e.g. ``"simulate"`` or ``"simulate and reduce"``.

    Raises
    ------
    ArtifactError
    """
    if list(input_names) != cfg.model.input_names:
        raise ArtifactError(f"{path}: inputs are {list(input_names)}, the config's are "
                            f"{cfg.model.input_names}; re-run {rerun}")
    times = cfg.model.output.times.times
    time = np.asarray(time)
    if time.shape != times.shape or not np.allclose(time, times):
        raise ArtifactError(f"{path}: made for a time grid of {time.size} samples "
                            f"({time[0]:g}-{time[-1]:g} s), the config's model.output.times "
                            f"has {times.size}; re-run {rerun}")
    bounds = np.asarray(bounds)
    if bounds.shape != cfg.model.bounds.shape or not np.allclose(bounds, cfg.model.bounds):
        raise ArtifactError(f"{path}: made for the design box {bounds.tolist()}, the config's "
                            f"input ranges are {cfg.model.bounds.tolist()}; re-run {rerun}")


def write_surrogate(path, s: Surrogate, val: Validation, cfg: Config, inputs,
                    channels: dict | None = None) -> None:
    """Write ``surrogate.h5``: the output's surrogate at the root, each further channel's
    (``channels``: name -> (Surrogate, Validation)) under ``/channels/<name>``."""
    with artifacts.write_artifact(path, "surrogate", config=cfg.section_yaml(*SECTIONS),
                                  inputs=inputs) as f:
        _put_surrogate(f, s, val)
        f.attrs["channels"] = json.dumps(list(channels or {}))
        for ch, (cs, cv) in (channels or {}).items():
            _put_surrogate(f.create_group(f"channels/{ch}"), cs, cv)


def _put_surrogate(f, s: Surrogate, val: Validation) -> None:
    """One surrogate's attributes and arrays into a group (the file's root or a channel's)."""
    f.attrs["input_names"] = json.dumps(s.input_names)
    f.attrs["kernel"] = s.kernel
    f.attrs["trend"] = s.trend
    f.attrs["transform"] = s.transform
    f.attrs["output_units"] = s.units
    f.attrs["validation"] = artifacts.json_attr(val.as_dict())
    f.attrs["content_id"] = s.fingerprint()
    put = artifacts.put
    put(f, "time", s.time, "s", "sample times")
    put(f, "bounds", s.bounds, "input units", "training box, rows (low, high) per input")
    zu = f"log({s.units})" if s.transform == "log" else s.units
    put(f, "mean", s.mean, zu, "mean training transient (after the transform)")
    put(f, "basis", s.basis, zu, "lifting of mode coefficients: z = mean + xi @ basis")
    put(f, "eigenvalues", s.eigenvalues, f"({zu})^2", "Karhunen-Loeve eigenvalues")
    put(f, "truncation_var", s.truncation_var, f"({zu})^2",
        "training variance not captured by the kept modes, per time step")
    put(f, "X_train", s.X_train, "1", "training inputs scaled to the unit box")
    put(f, "xi_train", s.xi_train, "1", "mode coefficients of the training transients")
    put(f, "scales", s.scales, "1 (unit box)", "kernel scale per mode and input")
    put(f, "amplitudes", s.amplitudes, "1", "kernel amplitude per mode")
    put(f, "X_test", s.X_test, "input units", "held-out test inputs, one row per FMU run")
    put(f, "Y_test", s.Y_test, s.units, "held-out FMU transients of the test inputs")
    g = f.create_group("trend_coefficients")
    for k, c in enumerate(s.trend_coefs):
        put(g, str(k), c, "1", f"trend coefficients of mode {k}")


def read_surrogate(path: str | os.PathLike) -> Surrogate:
    """Rebuild the output's surrogate from ``surrogate.h5`` (schema checked); its
    ``channel_names`` lists the further channels the file holds."""
    path = Path(path)
    with artifacts.open_artifact(path, "surrogate") as f:
        s = _get_surrogate(f, path)
        s.channel_names = json.loads(f.attrs.get("channels", "[]"))
        return s


def read_channel_surrogates(path: str | os.PathLike,
                            names: list[str] | None = None) -> dict[str, Surrogate]:
    """The further channels' surrogates of ``surrogate.h5``: ``names`` (default: all).

    Raises
    ------
    ArtifactError
        A named channel has no surrogate in the file (written before channels were
        reduced, or left out by ``reduce.channels``).
    """
    path = Path(path)
    with artifacts.open_artifact(path, "surrogate") as f:
        have = json.loads(f.attrs.get("channels", "[]"))
        out = {}
        for ch in (have if names is None else names):
            if ch not in have or f"channels/{ch}" not in f:
                raise ArtifactError(f"{path}: no surrogate of channel {ch!r} (the file has "
                                    f"{', '.join(have) or 'none'}); re-run simulate and reduce "
                                    "with the channel in model.channels (and reduce.channels)")
            out[ch] = _get_surrogate(f[f"channels/{ch}"], path)
        return out


def _get_surrogate(f, path: Path) -> Surrogate:
    """A surrogate from the group :func:`_put_surrogate` wrote."""
    get = lambda name: artifacts.get(f, name, path)  # noqa: E731
    K = get("basis").shape[0]
    coefs = [artifacts.get(f["trend_coefficients"], str(k), path) for k in range(K)]
    return Surrogate(input_names=json.loads(f.attrs["input_names"]), bounds=get("bounds"),
                     time=get("time"), mean=get("mean"), basis=get("basis"),
                     eigenvalues=get("eigenvalues"), truncation_var=get("truncation_var"),
                     X_train=get("X_train"), xi_train=get("xi_train"),
                     kernel=str(f.attrs["kernel"]), trend=str(f.attrs["trend"]),
                     scales=get("scales"), amplitudes=get("amplitudes"),
                     trend_coefs=coefs, transform=str(f.attrs["transform"]),
                     units=str(f.attrs["output_units"]),
                     X_test=get("X_test") if "X_test" in f else np.empty((0, 0)),
                     Y_test=get("Y_test") if "Y_test" in f else np.empty((0, 0)),
                     content_id=str(f.attrs.get("content_id", "")))


def read_validation(path: str | os.PathLike) -> dict:
    """The output surrogate's validation on the test runs (:meth:`Validation.as_dict`)."""
    with artifacts.open_artifact(path, "surrogate") as f:
        return json.loads(f.attrs["validation"])


def read_channel_validation(path: str | os.PathLike) -> dict[str, dict]:
    """Each further channel's validation on the test runs, by channel ({} when none)."""
    with artifacts.open_artifact(path, "surrogate") as f:
        return {ch: json.loads(f[f"channels/{ch}"].attrs["validation"])
                for ch in json.loads(f.attrs.get("channels", "[]"))}
