"""The fleet's prior of the trend shapes: how often its units' wear follows a line, a
quadratic, an exponential of each growth rate, a power law of each exponent, or a change,
learnt from the fleet.

The laplace method weighs each unit's trend shapes (:mod:`.shapes`) under the prior
probabilities ``calibrate.shapes``, the accelerating shape shared equally by its forms
(:func:`~.shapes.form_priors`). Ten years of one unit cannot tell a quadratic from an
exponential, nor one growth rate from the next: each form fits the record about as well,
and they part only in the forecast (on benchmarks/prognosis.py's quadratic fleet, seed 11,
the units' forecasts ran a year early under the exponential forms' equal share). The units
of a fleet share their wear mechanisms (duty, design, environment) far better than one
record shows them, and the evidence each unit holds adds up over the fleet: the quadratic
fleets of that benchmark put the fleet's weight on the quadratic and the slowest growth
rate, the exponential one on the growth rate 0.3.

The fleet's prior (empirical Bayes): each draw's form ``f`` (:func:`~.shapes.form_of`) has
prior probability ``pi_f``, the same for every unit, chosen to maximise the fleet's
marginal likelihood times a Dirichlet prior centred on the calibration's ``b_f``. Each
unit's marginal likelihood under ``pi``, relative to its calibration's, is known from its
own posterior draws (their forms' shares ``s_uf``), so no unit is calibrated again::

    p(y_u | pi) / p(y_u | b) = sum_{f in A_u} s_uf pi_f / b_f  *  sum_{A_u} b / sum_{A_u} pi

(``A_u``: the forms the unit's segment allows, :func:`~.shapes.available_forms`; a unit too
short for a shape says nothing of it). The Dirichlet's parameters are ``1 + m b_f``: the
calibration's prior counts as ``m`` units (:data:`PRIOR_UNITS`), so that a form the fleet
shows no sign of keeps a share a unit's own strong evidence can still take, and a small
fleet stays near the calibration's prior. Each unit's draws are then weighted by
``pi_f / b_f`` and resampled (:mod:`twinmon.forecast.pooling`, with the fleet's sigma).
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The calibration's prior counts as this many units of the fleet (the Dirichlet's
#: concentration beyond its flat part): one per form, so that the prior alone does not leave
#: a form's proportion at 0. Set before the benchmark's runs and not tuned (other values
#: not measured; docs/forecast.md, *A fleet-level prior of the trend shapes*).
PRIOR_UNITS = 8.0


@dataclass(frozen=True)
class FleetShapes:
    """The fleet's prior probabilities of the trend forms (the module's docstring).

    Attributes
    ----------
    proportions : ndarray, shape [F]
        ``pi``: the fleet's prior of each form (:func:`~.shapes.form_names`); sums to 1.
    base : ndarray, shape [F]
        ``b``: the calibration's (:func:`~.shapes.form_priors` of ``calibrate.shapes``).
    n_units : int
        Units it was fitted on.
    prior_units : float
        ``m``, the weight of ``b`` in units.
    """

    proportions: np.ndarray
    base: np.ndarray
    n_units: int
    prior_units: float

    def log_weights(self, forms: np.ndarray) -> np.ndarray:
        """``log(pi_f / b_f)`` of draws of forms ``forms`` [n] (indices): the log weight
        that takes a unit's draws from the calibration's prior to the fleet's, up to a
        constant [n]."""
        ok = self.base > 0
        ratio = np.full(self.base.size, -np.inf)
        ratio[ok] = np.log(self.proportions[ok]) - np.log(self.base[ok])
        return ratio[np.asarray(forms, int)]

    def shape_priors(self) -> dict:
        """The fleet's prior of the three shapes of ``calibrate.shapes`` (line,
        accelerating: its forms summed, change)."""
        p = self.proportions
        return {"line": float(p[0]), "accelerating": float(p[1:-1].sum()),
                "change": float(p[-1])}


def _neg_log_posterior(z: np.ndarray, S: np.ndarray, A: np.ndarray, b: np.ndarray,
                       m: float) -> tuple[float, np.ndarray]:
    """Minus the log of the fleet's marginal likelihood times the Dirichlet prior, at the
    forms' logits ``z`` [F'] (the forms of positive ``b``), and its gradient [F'].

    ``S`` [U, F'] the units' shares of their draws per form, ``A`` [U, F'] the forms their
    segments allow. With ``pi = softmax(z)``, per unit: ``r = S pi / b`` normalised (the
    draws' responsibilities) and ``q = A pi`` normalised; ``d/d log pi_f`` of the unit's
    term is ``r_f - q_f``, of the prior's ``m b_f``; through the softmax
    ``d/dz = g - pi sum(g)``."""
    pi = np.exp(z - z.max())
    pi /= pi.sum()
    num = S * (pi / b)                                                       # [U, F']
    top = num.sum(axis=1)
    den = (A * pi).sum(axis=1)
    value = np.sum(np.log(top)) - np.sum(np.log(den)) + m * float(b @ np.log(pi))
    g = (num / top[:, None]).sum(axis=0) - (A * pi / den[:, None]).sum(axis=0) + m * b
    return -value, -(g - pi * g.sum())


def fit_fleet_shapes(shares: np.ndarray, available: np.ndarray, base: np.ndarray,
                     prior_units: float = PRIOR_UNITS) -> FleetShapes:
    """The fleet's prior of the trend forms by maximum posterior (the module's docstring).

    Parameters
    ----------
    shares : ndarray, shape [U, F]
        Each unit's posterior share of its draws per form (rows sum to 1), under the
        calibration's prior ``base``.
    available : ndarray of bool, shape [U, F]
        The forms each unit's segments allow (:func:`~.shapes.available_forms`).
    base : ndarray, shape [F]
        The calibration's prior of each form (:func:`~.shapes.form_priors`); a form of
        prior 0 was never drawn and stays at 0.
    prior_units : float
        ``m``: the calibration's prior counts as this many units.

    Returns
    -------
    FleetShapes
    """
    # Imported here, as in fleet.py: the forecast's workers read this module's prior
    # without fitting it, and scipy.optimize takes 0.7 s to import.
    from scipy.optimize import minimize
    base = np.asarray(base, float)
    ok = base > 0
    S = np.asarray(shares, float)[:, ok]
    A = np.asarray(available, bool)[:, ok].astype(float)
    b = base[ok] / base[ok].sum()
    # A unit with no draw on the forms kept (none: every form it drew has prior > 0) or
    # one form available says nothing about the proportions.
    use = (S.sum(axis=1) > 0) & (A.sum(axis=1) > 1)
    S, A = S[use] / S[use].sum(axis=1, keepdims=True), A[use]
    r = minimize(_neg_log_posterior, np.log(b), args=(S, A, b, float(prior_units)),
                 method="L-BFGS-B", jac=True)
    pi = np.exp(r.x - r.x.max())
    out = np.zeros(base.size)
    out[ok] = pi / pi.sum()
    return FleetShapes(proportions=out, base=base, n_units=int(use.sum()),
                       prior_units=float(prior_units))
