"""The ``calibrate`` section: the Bayesian calibration per unit and year, its sampler, its
convergence and goodness-of-fit marks, and where it runs."""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, Optional

import numpy as np

#: ``calibrate.shapes``' default: the straight line a priori 3 times as likely as each
#: other shape (docs/calibration.md, "Trend shapes").
DEFAULT_SHAPES = {"line": 0.6, "accelerating": 0.2, "change": 0.2}


@dataclass(frozen=True)
class CalibrateConfig:
    """Bayesian calibration per unit and year (see docs/calibration.md).

    ``samples`` and ``burn_in`` count draws per chain; year-1 chains (uniform prior, a
    longer and more curved posterior) run twice as long and keep every second draw."""

    chains: int = 4
    samples: int = 1500
    burn_in: int = 250
    #: Width (std) of the Gaussian prior of year n+1 around year n's estimate, as a
    #: fraction of each input's design range. See docs/calibration.md for the default.
    prior_width: float = 0.05
    #: Output noise standard deviation (output units), for units whose observations file does not
    #: record one; None: estimated from the residuals of a least-squares fit of each year.
    noise_std: Optional[float] = None
    #: Add the previous year's posterior variance to the year-to-year prior variance (the
    #: Kalman predictive variance of a random walk): prior std = sqrt((w * range)^2 + var).
    prior_carry_variance: bool = True
    rhat_warn: float = 1.05
    ess_warn: float = 400.0
    #: A year whose R-hat or ESS misses the marks above is sampled again with chains twice
    #: as long (thinned to the same number of kept draws), at most this many times; still
    #: poor after that, the year is "unconverged" and its unit's prognosis "unreliable".
    max_extensions: int = 2
    #: Goodness of fit (docs/calibration.md): a year "misses the plant" when the RMS of its
    #: standardised residual at the posterior mean exceeds ``fit_min_rms`` (in noise standard
    #: deviations) AND the chi-square or Ljung-Box test rejects at ``fit_alpha``.
    fit_alpha: float = 1e-3
    fit_min_rms: float = 1.5
    #: A year sits "on the box edge" when more than ``edge_share`` of its posterior draws lie
    #: within ``edge_margin`` (fraction of the input's range) of a bound of the design box.
    edge_margin: float = 0.02
    edge_share: float = 0.25
    #: Pooled draws per year stored in ``posterior.h5``, evenly thinned over every chain; the
    #: summary statistics use every draw. 1000 keeps about all the effective samples (bulk
    #: ESS 600-1800 of 6000 draws with the defaults) and twice forecast's ``observed_samples``
    #: (docs/calibration.md, "Stored draws").
    keep_draws: int = 1000
    #: Worker processes (units run in parallel); 0 means one per core, 1 runs in-process.
    workers: int = 0
    #: ``dask``: the chains run on a Dask cluster (the ``dask`` section; docs/cluster.md).
    executor: Literal["process", "dask"] = "process"
    #: Further channels (keys of ``model.channels``) in the likelihood besides the output,
    #: each with its own noise; None: every channel the observations carry and the surrogate
    #: models; []: the output only.
    channels: Optional[tuple[str, ...]] = None
    #: How either method samples: ``vectorised`` (numpy, every unit's chains at once:
    #: random-walk Metropolis run until the ESS is met, calibrate/samplers/vectorised.py, or
    #: the joint method's Gibbs sweeps, calibrate/samplers/joint_vectorised.py) or
    #: ``openturns`` (OpenTURNS' samplers, one chain per task: the reference). Same model,
    #: same diagnostics; docs/calibration.md compares them.
    sampler: Literal["vectorised", "openturns"] = "vectorised"
    #: ``sequential``: the paper's method, each year sampled in turn with a prior centred on
    #: the previous year's estimate (calibrate/methods/sequential.py). ``joint``: each
    #: unit's whole history in one posterior with a linear trend per input (restarted at
    #: maintenance events) and its year-to-year scatter inside, sampled by Gibbs
    #: (calibrate/methods/joint.py; docs/calibration.md). ``laplace``: the same model drawn
    #: without a chain -- each year's likelihood summarised by a Gaussian, refined by
    #: expectation propagation, the draws importance-weighted back to the exact likelihood
    #: (calibrate/methods/laplace.py); on benchmarks/prognosis.py it gives the joint
    #: method's figures at a fraction of its cost.
    #: ``auto``: ``laplace`` when the observations hold a fleet whose year-to-year sd
    #: ``forecast`` can pool (``forecast.pool_sigma`` and at least ``forecast.pool_min_units``
    #: units), else ``sequential``: on benchmarks/prognosis.py the pooled joint model is
    #: the better calibrated one, the unpooled one is not (docs/forecast.md, "The default
    #: method").
    method: Literal["auto", "sequential", "joint", "laplace"] = "auto"
    #: ``joint`` only: moves of the whole trend (levels, slopes, scatter) per Gibbs sweep,
    #: each one surrogate call over the unit's years; the years' own moves are one each.
    joint_trend_moves: int = 5
    #: ``laplace`` only: the shapes each input's current trend segment may take, with their
    #: prior probabilities (calibrate/shapes.py; docs/calibration.md, "Trend shapes"):
    #: ``line``, ``accelerating`` (a quadratic term) and ``change`` (the level and the rate
    #: change in one year). The posterior averages them by their evidence; ``{line: 1}`` is
    #: the straight line alone.
    shapes: dict[str, float] = field(default_factory=lambda: dict(DEFAULT_SHAPES))

    def _check(self):
        from ..calibrate.shapes import SHAPES
        for name, p in self.shapes.items():
            if name not in SHAPES:
                yield f"shapes.{name}", f"is not a shape (choose from {', '.join(SHAPES)})", p
            elif not (np.isfinite(p) and p >= 0):
                yield f"shapes.{name}", "must be a finite probability >= 0", p
        if sum(p for p in self.shapes.values() if np.isfinite(p) and p > 0) <= 0:
            yield "shapes", "must give one shape a probability > 0", dict(self.shapes)
        if self.chains < 2:
            yield "chains", "must be >= 2 (split R-hat needs several chains)", self.chains
        if self.samples < 100:
            yield "samples", "must be >= 100", self.samples
        if self.burn_in < 0:
            yield "burn_in", "must be >= 0", self.burn_in
        if self.prior_width <= 0:
            yield "prior_width", "must be > 0", self.prior_width
        if self.noise_std is not None and self.noise_std <= 0:
            yield "noise_std", "must be > 0 (or null to estimate it)", self.noise_std
        if self.rhat_warn <= 1:
            yield "rhat_warn", "must be > 1", self.rhat_warn
        if self.ess_warn < 0:
            yield "ess_warn", "must be >= 0", self.ess_warn
        if self.workers < 0:
            yield "workers", "must be >= 0", self.workers
        if self.keep_draws < 1:
            yield "keep_draws", "must be >= 1", self.keep_draws
        if self.max_extensions < 0:
            yield "max_extensions", "must be >= 0", self.max_extensions
        if self.joint_trend_moves < 1:
            yield "joint_trend_moves", "must be >= 1", self.joint_trend_moves
        if not 0 < self.fit_alpha < 1:
            yield "fit_alpha", "must lie in (0, 1)", self.fit_alpha
        if self.fit_min_rms < 1:
            yield "fit_min_rms", "must be >= 1 (a residual at the noise level fits)", \
                self.fit_min_rms
        if not 0 <= self.edge_margin < 0.5:
            yield "edge_margin", "must lie in [0, 0.5)", self.edge_margin
        if not 0 < self.edge_share <= 1:
            yield "edge_share", "must lie in (0, 1]", self.edge_share
