"""The health indicator and the safety criterion, both declared in the config.

The indicator is one number per recorded transient (``safety.indicator``): the time a
variable takes to reach a level, its value at a time, its max / min / mean over a window, or
its final value. A unit is unsafe when that number passes ``safety.unsafe_if`` (above or
below a limit) or when its twin is non-physical; its failure year is the first year in which
the probability of being unsafe exceeds ``safety.failure_probability``.

Nothing here knows which machine it judges: the pump's t90 > 30 s is
``{kind: time_to_reach, level: 360, initial: 0}`` with ``unsafe_if: {above: 30}``.
"""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import numpy as np

from .config import Config, IndicatorSpec, SafetyConfig

_KIND_WORDS = {"time_to_reach": "time to reach {level:g} {vunits}", "value_at": "{var} at {at:g} s",
               "max": "maximum of {var}", "min": "minimum of {var}", "mean": "mean of {var}",
               "final": "final {var}"}


def compute_indicator(time: np.ndarray, values: np.ndarray, spec: IndicatorSpec) -> np.ndarray:
    """The health indicator of transients.

    Parameters
    ----------
    time : ndarray, shape [n_t]
        Sample times (s), increasing.
    values : ndarray, shape [..., n_t]
        The indicator's variable at those times (its own units). NaN marks a missing
        sample: it is skipped (a crossing is interpolated between the samples around it).
    spec : IndicatorSpec

    Returns
    -------
    ndarray, shape [...]
        The indicator (s for ``time_to_reach``, else the variable's units). For
        ``time_to_reach``: ``inf`` where the level is never reached within the record.
        NaN where a transient has no usable sample.
    """
    t = np.asarray(time, float)
    v = np.asarray(values, float)
    kind = spec.kind
    if kind == "time_to_reach":
        return _time_to_reach(t, v, spec)
    with np.errstate(invalid="ignore", divide="ignore"), _quiet_nan():
        if kind == "value_at":
            return _value_at(t, v, float(spec.at))
        if kind == "final":
            return _last_finite(v)
        lo, hi = spec.window if spec.window is not None else (-np.inf, np.inf)
        sel = (t >= lo) & (t <= hi)
        w = v[..., sel]
        if kind == "max":
            return np.nanmax(w, axis=-1) if w.shape[-1] else np.full(v.shape[:-1], np.nan)
        if kind == "min":
            return np.nanmin(w, axis=-1) if w.shape[-1] else np.full(v.shape[:-1], np.nan)
        return np.nanmean(w, axis=-1)
    raise ValueError(f"unknown indicator kind {kind!r}")  # the config rejects it first


class _quiet_nan:
    """Silence numpy's all-NaN warnings: a NaN result already says it."""

    def __enter__(self):
        import warnings
        self._w = warnings.catch_warnings()
        self._w.__enter__()
        warnings.simplefilter("ignore", RuntimeWarning)

    def __exit__(self, *exc):
        self._w.__exit__(*exc)


def _time_to_reach(t: np.ndarray, v: np.ndarray, spec: IndicatorSpec) -> np.ndarray:
    level = float(spec.level)
    sign = 1.0 if spec.direction == "up" else -1.0
    # A transient without one usable sample (a failed run) has no indicator, whatever the
    # known value at t = 0 says.
    empty = ~np.isfinite(v).any(axis=-1) if v.shape[-1] else np.ones(v.shape[:-1], bool)
    if spec.initial is not None:
        # A start from rest: the value at t = 0 is known, so an early crossing is
        # interpolated from it instead of being reported at the first sample.
        t = np.concatenate([[0.0], t])
        v = np.concatenate([np.full(v.shape[:-1] + (1,), float(spec.initial)), v], axis=-1)
    out = np.full(v.shape[:-1], np.inf)
    if v.shape[-1] == 0:
        return out
    flat = v.reshape(-1, v.shape[-1])
    res = out.reshape(-1)
    has_nan = np.isnan(flat).any(axis=1)
    # Fast path (no missing samples): vectorised first crossing.
    full = np.flatnonzero(~has_nan)
    if full.size:
        f = sign * flat[full]
        above = f >= sign * level
        reached = above.any(axis=1)
        k = np.argmax(above, axis=1)
        kk = np.maximum(k, 1)
        f1 = np.take_along_axis(f, (kk - 1)[:, None], 1)[:, 0]
        f2 = np.take_along_axis(f, kk[:, None], 1)[:, 0]
        with np.errstate(invalid="ignore", divide="ignore"):
            frac = np.where(f2 > f1, (sign * level - f1) / (f2 - f1), 1.0)
        tc = t[kk - 1] + np.clip(frac, 0.0, 1.0) * (t[kk] - t[kk - 1])
        tc = np.where(k == 0, t[0], tc)        # reached at the first (known) sample
        res[full] = np.where(reached, tc, np.inf)
    for i in np.flatnonzero(has_nan):
        ok = ~np.isnan(flat[i])
        if ok.sum() == 1:
            res[i] = t[ok][0] if sign * flat[i, ok][0] >= sign * level else np.inf
        elif ok.any():
            sub = IndicatorSpec(kind="time_to_reach", level=level, direction=spec.direction)
            res[i] = _time_to_reach(t[ok], flat[i, ok], sub)
    res = res.reshape(v.shape[:-1])
    return np.where(empty, np.nan, res)


def _value_at(t: np.ndarray, v: np.ndarray, at: float) -> np.ndarray:
    flat = v.reshape(-1, v.shape[-1])
    out = np.empty(flat.shape[0])
    for i, row in enumerate(flat):
        ok = ~np.isnan(row)
        out[i] = np.interp(at, t[ok], row[ok]) if ok.any() else np.nan
    return out.reshape(v.shape[:-1])


def _last_finite(v: np.ndarray) -> np.ndarray:
    ok = ~np.isnan(v)
    idx = v.shape[-1] - 1 - np.argmax(ok[..., ::-1], axis=-1)
    last = np.take_along_axis(v, idx[..., None], -1)[..., 0]
    return np.where(ok.any(axis=-1), last, np.nan)


def is_unsafe(value: np.ndarray, safety: SafetyConfig,
              nonphysical: np.ndarray | None = None) -> np.ndarray:
    """True where the indicator passes ``unsafe_if`` or the twin is non-physical.

    A NaN indicator (no usable sample) is not judged unsafe here: callers decide what a
    failed evaluation means (a failed FMU run counts as unsafe in ``forecast``)."""
    value = np.asarray(value, float)
    u = safety.unsafe_if
    with np.errstate(invalid="ignore"):
        bad = value > u.above if u.above is not None else value < u.below
    if nonphysical is not None:
        bad = bad | np.asarray(nonphysical, bool)
    return bad


def failure_year(years: np.ndarray, p_unsafe: np.ndarray, safety: SafetyConfig) -> int | None:
    """First year whose probability of being unsafe exceeds ``failure_probability``."""
    over = np.flatnonzero(np.asarray(p_unsafe) > safety.failure_probability)
    return int(years[over[0]]) if over.size else None


def trailing_run(years, flags) -> Optional[int]:
    """The first of the last ``years`` in a row whose ``flags`` hold, or None when the last
    one's does not (``years`` [n], ``flags`` [n] bool, in year order)."""
    flags = np.asarray(flags, bool)
    if not flags.size or not flags[-1]:
        return None
    off = np.flatnonzero(~flags)
    return int(np.asarray(years)[off[-1] + 1 if off.size else 0])


def median_failure_year(years: np.ndarray, p_unsafe: np.ndarray) -> int | None:
    """First year in which the unit is more likely unsafe than not (P(unsafe) >= 0.5).

    The point forecast of the failure year: the median of the time to failure when
    P(unsafe) grows with the years. :func:`failure_year` (P > ``failure_probability``, the
    paper's 5 %) is a low quantile of it -- the deadline for acting -- and falls before
    the median by as much as the forecast is uncertain, so it is the wrong number to score
    as a prediction of when the unit fails (``benchmarks/prognosis.py`` reports both)."""
    over = np.flatnonzero(np.asarray(p_unsafe) >= 0.5)
    return int(years[over[0]]) if over.size else None


def with_units(number: str, units: str) -> str:
    """``"14.5 s"``; a dimensionless quantity (units ``1`` or none) without units."""
    return number if units in ("", "1") else f"{number} {units}"


def check_against_grid(cfg: Config, spec: IndicatorSpec, time: np.ndarray) -> None:
    """Refuse indicator settings the record cannot answer (see :meth:`Indicator.from_config`).

    Parameters
    ----------
    time : ndarray, shape [n_t]
        Sample times of the record (s).
    """
    from .errors import ConfigError
    t = np.asarray(time, dtype=float)
    grid = f"the record (model.output.times) runs {t[0]:g}..{t[-1]:g} s in {t.size} samples"
    if spec.kind == "value_at" and spec.at is not None and not t[0] <= spec.at <= t[-1]:
        raise ConfigError(f"{cfg.source}: safety.indicator.at: {spec.at:g} s is outside the "
                          f"record; {grid}")
    if spec.kind in ("max", "min", "mean") and spec.window is not None:
        lo, hi = spec.window
        if not np.any((t >= lo) & (t <= hi)):
            raise ConfigError(f"{cfg.source}: safety.indicator.window: [{lo:g}, {hi:g}] s holds "
                              f"no sample time; {grid}")


@dataclass(frozen=True)
class Indicator:
    """The config's indicator with its resolved words, for computing and for reports.

    Attributes
    ----------
    spec : IndicatorSpec
    variable : str
        FMU variable it is computed from.
    name, label, units : str
        Short name, words, and units of the indicator.
    limit : float
        The ``unsafe_if`` value; ``sense`` +1 when above is unsafe, -1 when below is.
    """

    spec: IndicatorSpec
    safety: SafetyConfig
    variable: str
    name: str
    label: str
    units: str
    limit: float
    sense: int

    @classmethod
    def from_config(cls, cfg: Config) -> "Indicator":
        """The config's indicator, its settings checked against the record's time grid.

        Raises
        ------
        ConfigError
            A ``window`` that holds no sample time, or an ``at`` outside the record: every
            indicator would be NaN (or silently the value at an end of the record).
        """
        spec = cfg.safety.indicator
        check_against_grid(cfg, spec, cfg.model.output.times.times)
        var = cfg.indicator_variable
        vlabel, vunits = cfg.model.variable_words(var)
        units = spec.units or ("s" if spec.kind == "time_to_reach" else vunits)
        words = _KIND_WORDS[spec.kind].format(var=vlabel, level=spec.level or 0.0,
                                              at=spec.at or 0.0, vunits=vunits).strip()
        if spec.kind == "time_to_reach" and spec.direction == "down":
            words = words.replace("time to reach", "time to fall to")
        if spec.kind in ("max", "min", "mean") and spec.window is not None:
            words += f" over {spec.window[0]:g}-{spec.window[1]:g} s"
        label = spec.label or words
        name = spec.name or spec.kind.replace("_", " ")
        u = cfg.safety.unsafe_if
        return cls(spec, cfg.safety, var, name, label, units, float(u.limit), u.sense)

    def __call__(self, time: np.ndarray, values: np.ndarray) -> np.ndarray:
        """Indicator of transients [..., n_t] -> [...] (see :func:`compute_indicator`)."""
        return compute_indicator(time, values, self.spec)

    def unsafe(self, value: np.ndarray, nonphysical: np.ndarray | None = None) -> np.ndarray:
        return is_unsafe(value, self.safety, nonphysical)

    @property
    def rule(self) -> str:
        """The criterion in words, e.g. ``t90 above 30 s``."""
        side = "above" if self.sense > 0 else "below"
        return f"{self.name} {side} {with_units(f'{self.limit:g}', self.units)}"

    def fmt(self, value: float) -> str:
        """One indicator value for people: ``14.5 s``, ``never`` for a level not reached."""
        if value is None or not np.isfinite(value):
            if value is not None and np.isinf(value) and self.spec.kind == "time_to_reach":
                return "never reached"
            return "n/a"
        # Three significant digits, or as many as the integer part of the value or the limit
        # has (4339 beside a limit of 4335, not 4.34e+03).
        big = max(abs(float(value)), abs(float(self.limit)), 1.0)
        digits = max(3, int(np.floor(np.log10(big))) + 1)
        return with_units(f"{value:.{digits}g}", self.units)
