"""Outside the surrogate's box: a Gaussian-process model of the safety margin, learnt from
FMU runs, says which Monte Carlo points are surely unsafe; only the others run through the FMU.

A failing unit's future leaves the design box on its degrading side, where the indicator
is past its limit: on `benchmarks/fleet_scale.py`'s fleet about one future point in six is
outside the box, and running each through the FMU was three quarters of a forecast's CPU.
What ``P(unsafe)`` needs of such a point is the side of the limit it falls on. So, once per
forecast, :func:`build_limit_state` learns the margin to the limit over a region around the
box (active learning of the limit state, AK-MCS: Echard, Gayton and Lemaire, Structural
Safety 33, 2011): a Latin hypercube of FMU runs, then batches of runs where the model is
least sure of the side, until nearly every point of the region is told apart. A point is
then *surely unsafe* when the model's mean margin lies :data:`SURE` standard deviations
past the limit (a misclassification probability of 0.13 % under the model);
:meth:`LimitState.classify` returns those, with the model's estimate of their indicator.
Every other point outside the box -- safe or unsure, or beyond the region -- still runs
through the FMU, so the indicator of every safe point, and every quantile on the safe side
of the limit, is the FMU's own.

The model is built from the config (model, safety, FMU) and the forecast's seed alone, not
from the fleet: a unit's forecast does not depend on the other units. It checks itself by
leave-one-out on its own runs: how many sds past the limit a point must lie to be called
surely unsafe is raised until none of its own safe runs would have been; a model that would
need more than :data:`MAX_SURE`, whose kernel fit degenerates, or that is still unsure of
much of its region is not used (every outside point goes to the FMU, as with
``forecast.outside_box: fmu``).

The margin is ``sense (indicator - limit)`` in units of a scale ``S`` (the median distance of
the first runs' indicator from the limit), clipped below at ``-1`` (far on the safe side, the
value does not matter to the side) and above at the largest finite value the first runs saw,
the cap, where a failed run, a non-physical one and an indicator that is not finite on the
unsafe side (a level never reached) sit too: a plateau the model follows, not a jump it would
smooth over. A point surely at the cap is reported beyond every finite value (``+-inf``,
"never reached" for a time to reach a level).
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from ..config import Config

#: The region the model covers beyond the box, in box widths: on each input's degrading
#: side (where failing units' forecasts go) and on its healthy side (or both, for an input
#: whose direction is unknown: the larger).
DEGRADING_WIDTHS = 1.0
HEALTHY_WIDTHS = 0.5
#: A point is surely unsafe when its mean margin lies this many standard deviations past the
#: limit (more when the model's leave-one-out errors ask for it, up to ``MAX_SURE``; beyond
#: that the model is not used).
SURE = 3.0
MAX_SURE = 8.0
#: ... and its indicator known to this many margin units (one sd; a twentieth of the scale
#: ``S``, 0.6 s of t90 for the pump): a point sure of its side but not of its value (near
#: the level where the indicator stops being finite, say) goes to the FMU, so the quantiles
#: past the limit stay the FMU's to about that.
VALUE_SD = 0.05
#: Latin hypercube runs per input before the model's first fit.
INITIAL_RUNS_PER_INPUT = 24
#: Runs added per round where the model is least sure, and at most this many rounds of each
#: kind (side, then value).
BATCH = 8
MAX_ROUNDS = 12
#: Candidate points per input (uniform over the region outside the box) on which the model's
#: sureness is judged; the rounds stop when fewer than ``STOP_UNSURE`` of them are unsure.
CANDIDATES_PER_INPUT = 2000
STOP_UNSURE = 0.0005
#: The candidates' density beyond the box falls by e over this many box widths.
CANDIDATE_DECAY = 0.25
#: ... and the value rounds stop when fewer than this share of them are sure of their side
#: but not of their value.
STOP_VAGUE = 0.02
#: A model still unsure of more than this share of its candidates is not used.
MAX_UNSURE = 0.05
#: Margin clip on the safe side, in units of the scale.
SAFE_FLOOR = -1.0
#: Hyperparameter bounds of the kernel's scales on the region's unit cube.
SCALE_BOUNDS = (1e-2, 10.0)
#: Relative jitter on the kernel's diagonal (numerical stability of the Cholesky factor).
JITTER = 1e-10


def _matern52(U: np.ndarray, V: np.ndarray, scale: np.ndarray, amp2: float) -> np.ndarray:
    """OpenTURNS' ``MaternModel(scale, [amp], 2.5)`` between rows of U [m, d] and V [n, d]."""
    t = np.zeros((len(U), len(V)))
    for j in range(U.shape[1]):
        diff = (U[:, j, None] - V[None, :, j]) / scale[j]
        t += diff * diff
    t = np.sqrt(5.0 * t)
    return amp2 * (1.0 + t + t * t / 3.0) * np.exp(-t)


@dataclass
class LimitState:
    """The margin model of :func:`build_limit_state`.

    Attributes
    ----------
    lo, hi : ndarray, shape [d]
        The region it covers (input units); the design box lies inside.
    box_lo, box_hi : ndarray, shape [d]
        The surrogate's box. With a physical box its points are the surrogate's, never this
        model's; with a box that is not (``covers_box``), the model learnt it too, and tells
        which of its points are surely safe (hence physical: the surrogate's) and surely
        unsafe (its own).
    U : ndarray, shape [n, d]
        The runs' inputs on the region's unit cube.
    scale : ndarray, shape [d]; amplitude : float; beta : float
        Matern 5/2 kernel scales (unit cube), amplitude and constant trend (margin units).
    alpha : ndarray, shape [n]
        ``K^-1 (z - beta)``: the kriging weights of the mean.
    kinv : ndarray, shape [n, n]
        ``K^-1`` for the variance; ``kinv_1 = K^-1 1`` and ``ones_kinv_1 = 1' K^-1 1`` add
        the constant trend's own uncertainty (universal kriging).
    limit, sense : float, int
        The indicator's limit and +1 when above it is unsafe, -1 when below is.
    scale_ind : float
        ``S``: indicator units per margin unit.
    cap : float
        The largest finite margin the first runs saw (margin units): margins are clipped
        there, and a failed, non-physical or never-reached run has margin ``cap``.
    sure_sd, safe_sd : float
        How many sds past the limit (short of it) the mean margin must lie for a point to be
        surely unsafe (safe): ``SURE``, or more where the leave-one-out check asked for it.
    value_sd_factor : float
        The model's sd times this is the sd of its value (at least 1): the root mean square
        of the leave-one-out errors in their own sds, over the runs past the limit and below
        the cap.
    runs, rounds : int
        FMU runs spent and active-learning rounds made.
    unsure : float
        Share of the region's candidate points the model could not tell apart at the end.
    """

    lo: np.ndarray
    hi: np.ndarray
    box_lo: np.ndarray
    box_hi: np.ndarray
    U: np.ndarray
    scale: np.ndarray
    amplitude: float
    beta: float
    alpha: np.ndarray
    kinv: np.ndarray
    kinv_1: np.ndarray
    ones_kinv_1: float
    limit: float
    sense: int
    scale_ind: float
    cap: float
    sure_sd: float = SURE
    safe_sd: float = SURE
    value_sd_factor: float = 1.0
    covers_box: bool = False
    runs: int = 0
    rounds: int = 0
    unsure: float = float("nan")
    notes: list = field(default_factory=list)

    def _unit(self, X: np.ndarray) -> np.ndarray:
        return (X - self.lo) / (self.hi - self.lo)

    def in_region(self, X: np.ndarray) -> np.ndarray:
        """True per row [m] of X [m, d] (input units) inside the region the model covers."""
        return np.all((X >= self.lo) & (X <= self.hi), axis=1)

    def _kernel(self, X: np.ndarray) -> np.ndarray:
        return _matern52(self._unit(X), self.U, self.scale, self.amplitude ** 2)

    def mean(self, X: np.ndarray, k: Optional[np.ndarray] = None) -> np.ndarray:
        """The margin's mean at X [m, d] (input units), margin units. Each row is computed
        on its own (element-wise operations and per-row sums, no BLAS): a row's value does
        not depend on the batch it is in. ``k``: the kernel to the runs, if computed."""
        k = self._kernel(X) if k is None else k
        return self.beta + np.einsum("mn,n->m", k, self.alpha)

    def _trend_term(self, k: np.ndarray) -> np.ndarray:
        """The constant trend's share of the variance, ``(1 - k' K^-1 1)^2 / 1' K^-1 1``."""
        t = 1.0 - np.einsum("mn,n->m", k, self.kinv_1)
        return t * t / self.ones_kinv_1

    def sd(self, X: np.ndarray, k: Optional[np.ndarray] = None) -> np.ndarray:
        """The margin's standard deviation at X [m, d] (margin units), row by row."""
        k = self._kernel(X) if k is None else k
        # Two two-operand sums (as fast as a matrix product here, and row by row).
        quad = np.einsum("mk,mk->m", np.einsum("mn,nk->mk", k, self.kinv), k)
        var = self.amplitude ** 2 - quad + self._trend_term(k)
        return np.sqrt(np.maximum(var, 0.0))

    def classify(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Which rows of X [m, d] (input units, outside the box) are surely unsafe, and the
        model's indicator there.

        Returns
        -------
        sure : ndarray of bool, shape [m]
            Inside the region, the mean margin ``sure_sd`` sds past the limit, and its sd
            at most ``VALUE_SD`` (or the margin surely at the cap).
        value : ndarray, shape [m]
            The indicator's estimate where ``sure`` (its units; +-inf on the unsafe side
            where the margin surely reaches the cap: beyond every value the runs saw, or a
            failed / non-physical / never-reached run), NaN elsewhere.
        """
        X = np.atleast_2d(np.asarray(X, float))
        sure = np.zeros(len(X), bool)
        value = np.full(len(X), np.nan)
        idx = np.flatnonzero(self.in_region(X))
        if not idx.size:
            return sure, value
        k = self._kernel(X[idx])
        mu = self.mean(X[idx], k)
        sd = np.full(idx.size, np.inf)
        pos = np.flatnonzero(mu > 0)
        sd[pos] = self.sd(X[idx[pos]], k[pos])
        # Sure of the side, and of the value: its sd small, or surely failed / never reached.
        lower = mu - self.sure_sd * sd
        at_cap = lower > self.cap - 2 * VALUE_SD
        ok = (lower > 0) & ((self.value_sd_factor * sd <= VALUE_SD) | at_cap)
        j = idx[ok]
        sure[j] = True
        m = mu[ok]
        value[j] = np.where(at_cap[ok], self.sense * np.inf,
                            self.limit + self.sense * self.scale_ind * np.minimum(m, self.cap))
        return sure, value

    def surely_safe(self, X: np.ndarray) -> np.ndarray:
        """True per row [m] of X [m, d] (input units) inside the region whose mean margin
        lies ``safe_sd`` sds short of the limit: safe, and physical (a non-physical or
        failed run has the unsafe cap for margin). Row by row, as :meth:`classify`."""
        X = np.atleast_2d(np.asarray(X, float))
        out = np.zeros(len(X), bool)
        idx = np.flatnonzero(self.in_region(X))
        if idx.size:
            k = self._kernel(X[idx])
            mu = self.mean(X[idx], k)
            neg = np.flatnonzero(mu < 0)
            if neg.size:
                out[idx[neg]] = mu[neg] + self.safe_sd * self.sd(X[idx[neg]], k[neg]) < 0
        return out

    def as_dict(self) -> dict:
        """What the forecast's summary and artifact record of the model."""
        return {"runs": int(self.runs), "rounds": int(self.rounds),
                "unsure": round(float(self.unsure), 5),
                "region": {"low": [float(v) for v in self.lo],
                           "high": [float(v) for v in self.hi]},
                "sure_sd": round(float(self.sure_sd), 3),
                "safe_sd": round(float(self.safe_sd), 3), "covers_box": bool(self.covers_box),
                "value_sd_factor": round(float(self.value_sd_factor), 3),
                "notes": list(self.notes)}


def region(cfg: Config, directions: dict) -> tuple[np.ndarray, np.ndarray]:
    """The region around the design box the model covers (input units), from each input's
    degrading direction (:data:`DEGRADING_WIDTHS`, :data:`HEALTHY_WIDTHS`), within the range
    the FMU declares for it."""
    box = np.asarray(cfg.model.bounds, float)
    width = box[:, 1] - box[:, 0]
    sign = np.array([getattr(directions.get(n), "sign", 0) for n in cfg.model.input_names])
    up = np.where(sign > 0, DEGRADING_WIDTHS, np.where(sign < 0, HEALTHY_WIDTHS,
                                                       DEGRADING_WIDTHS))
    down = np.where(sign < 0, DEGRADING_WIDTHS, np.where(sign > 0, HEALTHY_WIDTHS,
                                                         DEGRADING_WIDTHS))
    lo, hi = box[:, 0] - down * width, box[:, 1] + up * width
    # An input whose whole box has one sign keeps it: a region that would cross zero stops
    # at half the bound nearest zero (a damping, a resistance or a friction coefficient
    # below zero is no machine at all, and its runs say nothing of the machine's limit).
    lo = np.where((box[:, 0] > 0) & (lo <= 0), box[:, 0] / 2, lo)
    hi = np.where((box[:, 1] < 0) & (hi >= 0), box[:, 1] / 2, hi)
    # Nor beyond the range the FMU declares (the forecast holds its draws there too).
    from ..simulate import declared_range
    declared = declared_range(cfg)
    return np.maximum(lo, declared[:, 0]), np.minimum(hi, declared[:, 1])


def forecast_limit_state(cfg: Config, directions: dict, box_ok: bool, spec=None
                         ) -> tuple[Optional[LimitState], str]:
    """The forecast's model of the points the surrogate cannot answer: built when
    ``forecast.outside_box`` is ``learn`` and the indicator is computed from the output the
    surrogate learnt; over the box too when the box is not physical (``box_ok`` false: the
    surrogate then answers only the points the model is sure are safe). None otherwise, or
    when it failed its check (with the reason, "" when it was not asked for)."""
    from ..safety import Indicator
    if (cfg.forecast.outside_box != "learn"
            or Indicator.from_config(cfg).variable != cfg.model.output.variable):
        return None, ""
    return build_limit_state(cfg, directions, spec, covers_box=not box_ok)


def build_limit_state(cfg: Config, directions: dict, spec=None, seed: Optional[int] = None,
                      covers_box: bool = False) -> tuple[Optional[LimitState], str]:
    """Learn the margin to the safety limit around the design box from FMU runs.

    Parameters
    ----------
    cfg : Config
    directions : dict input -> Direction
        :func:`~.directions.degrading_directions`: which side of the box the region
        extends further.
    spec : SimulationSpec, optional
        The FMU (default the config's).
    seed : int, optional
        Seed of the design and candidates (default ``cfg.seed``).
    covers_box : bool
        Learn the box as well (a box that is not physical: every point is the model's or
        the FMU's, but for those it is sure are safe).

    Returns
    -------
    LimitState or None
        None when the model failed its leave-one-out check (or could not be fitted): every
        point outside the box then goes to the FMU.
    str
        Why it is None ("" otherwise).
    """
    from ..executors import one_blas_thread
    from ..simulate import spec_for
    spec = spec or spec_for(cfg)
    with one_blas_thread():
        return _build(cfg, directions, spec, seed, covers_box)


def _build(cfg: Config, directions: dict, spec, seed, covers_box: bool
           ) -> tuple[Optional[LimitState], str]:
    from ..executors import SerialExecutor
    rng = np.random.default_rng([cfg.seed if seed is None else seed, 8191])
    lo, hi = region(cfg, directions)
    box = np.asarray(cfg.model.bounds, float)
    d = len(lo)
    ex = SerialExecutor(keep_open=True)
    try:
        runs = _Runs(cfg, spec, ex)
        X = lo + _lhs(INITIAL_RUNS_PER_INPUT * d, d, rng) * (hi - lo)
        ind, bad = runs(X)
        scale_ind, cap = _margin_scale(ind, bad, runs.limit, runs.sense)
        z = _margin(ind, bad, runs.limit, runs.sense, scale_ind, cap)
        try:
            hyper = _fit_hyper((X - lo) / (hi - lo), z)
        except Exception as exc:      # OpenTURNS' optimiser: a model we cannot fit is not used
            return None, f"the limit-state model could not be fitted ({exc})"
        if np.any(hyper[0] <= SCALE_BOUNDS[0] * 1.01):
            return None, ("the limit-state model could not be fitted (a kernel scale at its "
                          "lower bound: the margin looks like noise at the scale of its runs)")
        model = _condition(lo, hi, box, X, z, hyper, runs, scale_ind, cap)
        cand = _candidates(lo, hi, box, CANDIDATES_PER_INPUT * d, rng, covers_box)
        rounds = 0
        for goal in ("side", "value"):
            # First where the model is least sure of the side (AK-MCS's learning function),
            # then, on the unsafe side, where it is least sure of the value.
            for _ in range(MAX_ROUNDS):
                k = model._kernel(cand)
                mu, sd = model.mean(cand, k), _sd_matrix(model, k)
                u = np.abs(mu) / np.maximum(sd, 1e-300)
                if goal == "side":
                    model.unsure = float(np.mean(u < SURE))
                    if model.unsure < STOP_UNSURE:
                        break
                    score = u
                else:
                    lower = mu - SURE * sd
                    vague = (lower > 0) & (sd > VALUE_SD) & (lower <= cap - 2 * VALUE_SD)
                    if np.mean(vague) < STOP_VAGUE:
                        break
                    score = np.where(mu > 0, -sd, np.inf)
                pick = _spread(cand, score, BATCH, (hi - lo))
                i_new, b_new = runs(cand[pick])
                X = np.vstack([X, cand[pick]])
                z = np.concatenate([z, _margin(i_new, b_new, runs.limit, runs.sense,
                                               scale_ind, cap)])
                cand = np.delete(cand, pick, axis=0)
                rounds += 1
                model = _condition(lo, hi, box, X, z, hyper, runs, scale_ind, cap)
        if rounds:
            # The kernel fitted again on every run: the rounds sharpened the limit.
            try:
                again = _fit_hyper((X - lo) / (hi - lo), z)
                if np.all(again[0] > SCALE_BOUNDS[0] * 1.01):
                    hyper = again
            except Exception:
                pass       # the first fit's kernel serves
            model = _condition(lo, hi, box, X, z, hyper, runs, scale_ind, cap)
            k = model._kernel(cand)
            model.unsure = float(np.mean(np.abs(model.mean(cand, k)) /
                                         np.maximum(_sd_matrix(model, k), 1e-300) < SURE))
        model.rounds = rounds
    finally:
        ex.close()
    if model.unsure > MAX_UNSURE:
        return None, (f"the limit-state model could not tell {100 * model.unsure:.0f} % of "
                      f"its region apart after {model.runs} FMU runs")
    need = _loo_sure_sd(model, z)
    if need > MAX_SURE:
        wrong = int(np.sum(_loo_u(model, z)[z <= 0] > MAX_SURE))
        return None, (f"the limit-state model would have called {wrong} of its own "
                      f"{len(z)} FMU runs surely unsafe ({MAX_SURE:g} sds past the limit) "
                      "when they were not (leave-one-out)")
    if need > SURE:
        model.sure_sd = need
        model.notes.append(f"its leave-one-out errors ask for {need:.2f} sds past the limit "
                           f"instead of {SURE:g}")
    model.value_sd_factor = _loo_value_factor(model, z)
    model.covers_box = covers_box
    if covers_box:
        # It also says which points are safe: none of its unsafe runs may read so.
        need = _loo_sure_sd(model, z, safe=True)
        if need > MAX_SURE:
            return None, ("the limit-state model would have called some of its own FMU runs "
                          f"surely safe ({MAX_SURE:g} sds short of the limit) when they were "
                          "not (leave-one-out)")
        model.safe_sd = need
    return model, ""


class _Runs:
    """The FMU's indicator and its failed / non-physical flag at design points."""

    def __init__(self, cfg: Config, spec, executor):
        from ..safety import Indicator
        self.cfg, self.spec, self.executor = cfg, spec, executor
        self.ind = Indicator.from_config(cfg)
        self.limit, self.sense = float(self.ind.limit), int(self.ind.sense)
        self.count = 0

    def __call__(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        from ..simulate import as_parameters, run_batch
        batch = run_batch(self.spec, as_parameters(self.cfg, X), self.executor)
        self.count += len(X)
        value = np.where(batch.ok, self.ind(self.spec.times, batch.outputs[self.ind.variable]),
                         np.nan)
        bad = ~batch.ok
        if self.cfg.model.nonphysical:
            bad |= batch.ok & (batch.outputs[self.cfg.model.nonphysical][:, -1] > 0.5)
        return value, bad


def _margin_scale(value, bad, limit, sense) -> tuple[float, float]:
    """``S`` (the median distance of the finite indicators from the limit) and the cap (the
    largest finite margin seen, at least 1), from the first runs."""
    m = sense * (value - limit)
    fin = np.isfinite(m) & ~bad
    scale = float(np.median(np.abs(m[fin]))) if fin.any() else 1.0
    if not scale > 0:
        scale = float(np.max(np.abs(m[fin]))) if fin.any() and np.max(np.abs(m[fin])) > 0 \
            else 1.0
    cap = float(np.max(m[fin]) / scale) if fin.any() else 1.0
    return scale, max(cap, 1.0)


def _margin(value, bad, limit, sense, scale, cap) -> np.ndarray:
    """The runs' margins (:mod:`this module's docstring <.limitstate>`), margin units."""
    m = sense * (value - limit) / scale
    unsafe_nonfinite = ~np.isfinite(m) & (np.isnan(m) | (m > 0))
    z = np.clip(np.where(np.isfinite(m), m, SAFE_FLOOR), SAFE_FLOOR, cap)
    return np.where(bad | unsafe_nonfinite, cap, z)


def _lhs(n: int, d: int, rng) -> np.ndarray:
    """A Latin hypercube of n points on the unit cube [n, d]."""
    perm = np.argsort(rng.random((d, n)), axis=1).T
    return (perm + rng.random((n, d))) / n


def _candidates(lo, hi, box, n, rng, covers_box: bool = False) -> np.ndarray:
    """n points over the region outside the box (and in it, with ``covers_box``), denser
    near the box: a point's density falls as ``exp(-e / CANDIDATE_DECAY)`` with its distance
    e beyond the box (in box widths, the largest over the inputs), as a trend's draws thin
    out away from where it stands."""
    width = box[:, 1] - box[:, 0]
    out = []
    while sum(len(c) for c in out) < n:
        C = lo + rng.random((4 * n, len(lo))) * (hi - lo)
        e = np.max(np.maximum(box[:, 0] - C, C - box[:, 1]) / width, axis=1)
        keep = ((e > 0) | covers_box) & (rng.random(len(C)) <
                                          np.exp(-np.maximum(e, 0) / CANDIDATE_DECAY))
        out.append(C[keep])
    return np.concatenate(out)[:n]


def _spread(cand, u, k, width) -> np.ndarray:
    """k candidates where the model is least sure (smallest ``u``), each at least a tenth of
    the region's width from the others chosen (a batch that does not pile up)."""
    order = np.argsort(u, kind="stable")
    chosen = []
    for i in order:
        if all(np.max(np.abs(cand[i] - cand[j]) / width) > 0.1 for j in chosen):
            chosen.append(i)
            if len(chosen) == k:
                break
    return np.array(chosen, int)


def _fit_hyper(U: np.ndarray, z: np.ndarray) -> tuple[np.ndarray, float]:
    """Kernel scales and amplitude by maximum likelihood (OpenTURNS' ``GaussianProcessFitter``,
    Matern 5/2, constant trend) on the unit cube."""
    import openturns as ot
    d = U.shape[1]
    fitter = ot.GaussianProcessFitter(ot.Sample(U), ot.Sample(z[:, None]),
                                      ot.MaternModel([0.3] * d, [1.0], 2.5),
                                      ot.ConstantBasisFactory(d).build())
    fitter.setOptimizationBounds(ot.Interval([SCALE_BOUNDS[0]] * d, [SCALE_BOUNDS[1]] * d))
    # Cobyla's "maximum number of function evaluations" came to stderr in colour codes,
    # whatever -q said: the scales it stops at serve (the model answers only the points it
    # is sure of, by its own sd), so the line says nothing a user can act on.
    from ..reduce.surrogate import ot_log_captured
    with ot_log_captured():
        fitter.run()
    cov = fitter.getResult().getCovarianceModel()
    return np.array(cov.getScale(), float), float(cov.getAmplitude()[0])


def _condition(lo, hi, box, X, z, hyper, runs, scale_ind, cap) -> LimitState:
    """The model conditioned on the runs (X [n, d], margins z [n]) at fixed hyperparameters:
    generalised least squares for the constant trend, the kriging weights, ``K^-1``."""
    scale, amp = hyper
    U = (X - lo) / (hi - lo)
    n = len(U)
    K = _matern52(U, U, scale, amp * amp)
    K[np.diag_indices(n)] += JITTER * amp * amp
    L = np.linalg.cholesky(K)
    Linv = np.linalg.solve(L, np.eye(n))
    kinv = Linv.T @ Linv
    kinv_1 = kinv.sum(axis=1)
    ones_kinv_1 = float(kinv_1.sum())
    beta = float(kinv_1 @ z) / ones_kinv_1
    alpha = kinv @ (z - beta)
    return LimitState(lo=lo, hi=hi, box_lo=box[:, 0], box_hi=box[:, 1], U=U, scale=scale,
                      amplitude=amp, beta=beta, alpha=alpha, kinv=kinv, kinv_1=kinv_1,
                      ones_kinv_1=ones_kinv_1, limit=runs.limit, sense=runs.sense,
                      scale_ind=scale_ind, cap=cap, runs=runs.count)


def _sd_matrix(model: LimitState, k: np.ndarray) -> np.ndarray:
    """The margin's sd at the candidates whose kernel to the runs is k [m, n], by matrix
    products (the build runs once, on one BLAS thread)."""
    quad = np.sum((k @ model.kinv) * k, axis=1)
    return np.sqrt(np.maximum(model.amplitude ** 2 - quad + model._trend_term(k), 0.0))


def _loo_u(model: LimitState, z: np.ndarray) -> np.ndarray:
    """Each run's leave-one-out mean margin in its leave-one-out sds: closed form (Dubrule
    1983), mean ``z_i - alpha_i / Kinv_ii``, variance ``1 / Kinv_ii``."""
    diag = np.diag(model.kinv)
    return (z - model.alpha / diag) * np.sqrt(diag)


def _loo_value_factor(model: LimitState, z: np.ndarray) -> float:
    """How much larger the leave-one-out errors are than the model's sds, on the runs past
    the limit and below the cap (root mean square of the errors in sds; at least 1)."""
    diag = np.diag(model.kinv)
    err = (model.alpha / diag) * np.sqrt(diag)          # z_i - loo mean, in loo sds
    past = (z > 0) & (z < model.cap)
    return max(1.0, float(np.sqrt(np.mean(err[past] ** 2)))) if past.sum() >= 3 else 1.0


def _loo_sure_sd(model: LimitState, z: np.ndarray, safe: bool = False) -> float:
    """The sds past the limit at which leave-one-out calls none of the safe runs (margin at
    most 0) surely unsafe: ``SURE``, or a tenth more than the worst such run's. ``safe``:
    the sds short of it at which it calls none of the unsafe runs surely safe."""
    u = -_loo_u(model, z)[z > 0] if safe else _loo_u(model, z)[z <= 0]
    worst = float(u.max()) if u.size else -np.inf
    return max(SURE, 1.1 * worst)
