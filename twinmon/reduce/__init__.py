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

Layout: ``surrogate`` (the :class:`Surrogate`, :func:`fit_surrogate`,
:func:`validate_surrogate`), ``artifact`` (:func:`write_surrogate`, :func:`read_surrogate` and
the other readers); the stage function :func:`reduce` and its checks here.
"""
from __future__ import annotations

import dataclasses
import os
from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from .. import artifacts
from ..config import Config, ReduceConfig
from ..errors import ArtifactError, CalibrationError, ConfigError
from ..simulate import read_simulations
from .artifact import (SECTIONS, read_channel_surrogates, read_channel_validation,
                       read_surrogate, read_validation, write_surrogate)
from .surrogate import (Surrogate, Validation, fit_surrogate, resolve_transform,
                        validate_surrogate)

__all__ = ["SECTIONS", "Surrogate", "Validation", "ReduceSummary", "reduce", "fit_surrogate",
           "resolve_transform", "validate_surrogate", "cap_warning", "error_warning",
           "channels_to_reduce",
           "check_made_for", "write_surrogate", "read_surrogate", "read_channel_surrogates",
           "read_validation", "read_channel_validation"]


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
        except ConfigError as exc:
            # The config's choice, not the data's: exit 3, naming the config.
            raise ConfigError(f"{cfg.source}: {what}{exc.message} (the simulations in "
                              f"{simulations})") from None
        s.X_test, s.Y_test = sims.X["test"][okt], Y_test
        return s, validate_surrogate(s, s.X_test, s.Y_test)

    s, val = fit(sims.Y["train"][ok], sims.Y["test"][okt], cfg.reduce,
                 cfg.model.output.units, "")
    names, warnings = channels_to_reduce(cfg, sims)
    capped = cap_warning(s, cfg.reduce, val.max_range_error,
                         f"the output {cfg.model.output.name}")
    coarse = error_warning(val.max_range_error, val.mean_range_error,
                           f"the output {cfg.model.output.name}", capped)
    warnings = [capped] * bool(capped) + [coarse] * bool(coarse) + \
        [optimiser_warning(s, val, f"the output {cfg.model.output.name}")] \
        * bool(s.optimiser_stopped) + warnings
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
        coarse = error_warning(fitted[ch][1].max_range_error, fitted[ch][1].mean_range_error,
                               f"channel {ch}", capped)
        if coarse:
            warnings.append(coarse)
        if fitted[ch][0].optimiser_stopped:
            warnings.append(optimiser_warning(*fitted[ch], f"channel {ch}"))
    write_surrogate(output, s, val, cfg, [simulations], channels=fitted)
    return ReduceSummary(s.n_modes, s.variance_ratio, val, int(ok.sum()), str(output),
                         {ch: {"modes": c.n_modes, "variance_ratio": c.variance_ratio,
                               "transform": c.transform, "test": v.as_dict()}
                          for ch, (c, v) in fitted.items()}, warnings)


def optimiser_warning(s: "Surrogate", val: "Validation", what: str) -> str:
    """A warning that the hyperparameter search of some modes of ``what``'s surrogate
    stopped at its evaluation limit (OpenTURNS' Cobyla): their fit is kept, and its test
    error says whether that matters."""
    modes = ", ".join(map(str, s.optimiser_stopped))
    return (f"{what}: the Gaussian process of mode(s) {modes} of {s.n_modes} stopped its "
            "hyperparameter search at the evaluation limit (OpenTURNS Cobyla); the fit is "
            f"kept: its largest test error is {100 * val.max_range_error:.3g} % of the "
            "output's range")


#: Largest test error (fraction of the output's range) a surrogate may have without a
#: warning: beyond it the surrogate, not the data, shapes the calibrations (a four-input
#: drive's at 14 % named faults in six of its seven units).
MAX_TEST_ERROR = 0.05


def error_warning(max_range_error: Optional[float], mean_range_error: Optional[float],
                  what: str, capped: str = "") -> str:
    """A warning when a surrogate's largest test error (fraction of the output's range)
    exceeds :data:`MAX_TEST_ERROR` ("" otherwise, or when :func:`cap_warning` has said it
    already, ``capped``)."""
    if capped or not (max_range_error or 0.0) > MAX_TEST_ERROR:
        return ""
    mean = (f" (mean {100 * mean_range_error:.2g} %)" if mean_range_error is not None
            else "")
    return (f"{what}: the surrogate's largest error on the test runs is "
            f"{100 * max_range_error:.3g} % of the output's range{mean}: calibrations rest "
            "on it; more training "
            "runs (simulate.train_size) or modes (reduce.max_modes), or a narrower design "
            "box, make it smaller")


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
