"""What the calibration methods and the samplers share: the sequential prior, the chains'
starting points, the tasks a worker runs, OpenTURNS' adaptation constants, and the state of a
worker process (its surrogate, set up once by :func:`init_worker`)."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import numpy as np

from ..config import Config
from ..errors import CalibrationError, Interrupted
from .density import Prior

#: During the burn-in each chain's proposal scale is adapted every this many steps, as
#: OpenTURNS' random walk does (its defaults: period 30, range [0.117, 0.468], x1.2 / x0.8).
ADAPT_PERIOD, ADAPT_RANGE, ADAPT_UP, ADAPT_DOWN = 30, (0.117, 0.468), 1.2, 0.8


def yearly_noise(surrogate, noise_std, n_years: int) -> np.ndarray:
    """Each year's noise standard deviation: [n_years], or [n_years, n_ch] for a stacked
    surrogate (several channels take one noise each), broadcast from ``noise_std``."""
    n_ch = len(getattr(surrogate, "blocks", ()))
    return np.broadcast_to(np.asarray(noise_std, float),
                           (n_years, n_ch) if n_ch else (n_years,)).copy()


def initial_states(rng: np.random.Generator, x_map: np.ndarray, cov: np.ndarray,
                   prior: Prior, chains: int) -> np.ndarray:
    """Dispersed starting points: N(MAP, (2 sd)^2) draws kept inside the box."""
    L = np.linalg.cholesky(cov)
    out = []
    while len(out) < chains:
        x = x_map + 2.0 * L @ rng.standard_normal(len(x_map))
        if prior.inside(x)[0]:
            out.append(x)
        elif rng.random() < 0.05:  # stuck against a wall: fall back to the MAP itself
            out.append(x_map.copy())
    return np.array(out)


def year_prior(cfg: Config, previous: Optional[np.ndarray],
               previous_var: Optional[np.ndarray] = None) -> Prior:
    """Prior of a year: uniform on the box without a previous estimate, else Gaussian
    around it with ``prior_width * range`` (plus the previous posterior variance when
    ``calibrate.prior_carry_variance`` is set)."""
    bounds = cfg.model.bounds
    if previous is None:
        return Prior.uniform(bounds)
    var = (cfg.calibrate.prior_width * np.diff(bounds, axis=1).ravel()) ** 2
    if cfg.calibrate.prior_carry_variance and previous_var is not None:
        var = var + previous_var
    return Prior.gaussian(bounds, previous, np.sqrt(var))


@dataclass
class ChainTask:
    """Everything a worker needs to run one chain of one unit-year (picklable)."""

    prior: Prior
    obs_row: np.ndarray
    noise_var: np.ndarray
    start: np.ndarray
    proposal_cov: np.ndarray
    samples: int
    burn_in: int
    seed: int
    thin: int


@dataclass
class JointTask:
    """Everything a worker needs to run one Gibbs chain of one unit (picklable).

    ``obs`` [K, n_t] and ``noise_var`` [K, n_t] are the years' data and likelihood variances;
    ``X`` the per-input design matrices; ``slope_mean``/``slope_sd`` [d] and ``cauchy_scale``
    [d] the priors; ``start`` the initial state [D]; ``eps_cov`` [K, d, d] and ``trend_cov``
    [p, p] the proposals' covariances; ``trend_moves`` the trend's moves per sweep."""

    bounds: np.ndarray
    obs: np.ndarray
    noise_var: np.ndarray
    X: list
    slope_mean: np.ndarray
    slope_sd: np.ndarray
    cauchy_scale: np.ndarray
    start: np.ndarray
    eps_cov: np.ndarray
    trend_cov: np.ndarray
    trend_moves: int
    samples: int
    burn_in: int
    seed: int
    thin: int


# ---------------------------------------------------------------------------------------
# Worker processes
# ---------------------------------------------------------------------------------------
#: The state of a worker process: ``surrogate`` (set by :func:`init_worker`), and the
#: samplers' batch predictor made from it on first use.
worker: dict = {}


def init_worker(surrogate, surrogate_path, output: str = "", channels=()) -> None:
    """Set up a worker process of calibrate's pool (its initializer, module-level so that
    a process or Dask pool can pickle it): a forked worker gets the likelihood's
    ``surrogate`` itself, a spawned one (``surrogate`` None) rebuilds it from
    ``surrogate_path`` with the output and further ``channels``."""
    if surrogate is None:  # spawned, not forked: rebuild from the file
        from .channels import load_surrogate
        surrogate = load_surrogate(surrogate_path, output, list(channels))
    worker["surrogate"] = surrogate


def unit_groups(units: list, workers: int, most: int = 0) -> list[list]:
    """Units split into tasks: at least one per worker, up to four per worker when there are
    enough units for batches of ~64 (a batch of a few hundred chains keeps the numpy calls
    large; several tasks per worker keep the workers evenly busy), and at most ``most``
    units a task when given (a task's results are held whole until it is taken)."""
    n = max(workers, min(4 * workers, math.ceil(len(units) / 64)), 1)
    if most > 0:
        n = max(n, math.ceil(len(units) / most))
    size = math.ceil(len(units) / n)
    return [units[i:i + size] for i in range(0, len(units), size)]


def sampling_pool(pool, output):
    """``pool`` for calibrate's sampling (:func:`~twinmon.executors.closing_pool`): a dead
    worker or a Ctrl-C ends the stage with one line, nothing written."""
    from ..executors import closing_pool
    return closing_pool(
        pool, CalibrationError(f"{output}: a worker process died while sampling; nothing was "
                               "written; re-run with calibrate.workers=1 to see why"),
        Interrupted(f"{output}: interrupted; nothing was written"))
