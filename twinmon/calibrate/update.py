"""``calibrate --update``: continue an earlier posterior with the years added since.

The sequential method calibrates a unit's years in order, each year's prior built from the
year before (its posterior mean and variance), and draws year ``k`` of unit ``U`` from a
generator seeded by (``U``, ``k``) alone. So the years already in ``posterior.h5`` need not
be sampled again: a unit continues from its last stored year (mean, variance and, for the
vectorised sampler's warm start, each chain's last state, all stored bit for bit), and the
result is the one a full run would give, array for array. The kept years' draws are not
even read: the new posterior starts as a copy of the old file, each continued unit's record
is rewritten and its new years' draws appended (``write_posterior(base=...)``).

With the joint method (a unit's whole history in one posterior) a unit is kept as it is when
it has no new year, and calibrated again in full otherwise. The laplace method draws the same
joint model from a Gaussian site per year, and a year's site depends on that year's data
alone: a unit with new years keeps its stored years' sites (recorded bit for bit in its
record), summarises only the new years, and is drawn again from all of them with its own
seed, which gives the full run's arrays.

A unit is calibrated in full instead when it is new, when the data of a stored year changed
(each year's observation row and noise are recorded as a SHA-256: a corrected file, or a
noise estimated from all the unit's years, which moves when years are added), when its
stored years are not the first of its years now, or (joint and laplace methods, whose trend
restarts at them) when its maintenance events changed. Units no longer in the observations are
left out, as a full run would. An update is refused (``ArtifactError``) when the posterior
was made by another version of twinmon, with another ``model``/``calibrate``/``seed`` config,
through another surrogate, or before these records existed.
"""
from __future__ import annotations

import hashlib
import os
from pathlib import Path

import numpy as np
import yaml

from .. import artifacts
from ..config import Config
from ..errors import ArtifactError
from .base import Method
from .posterior import SECTIONS, UnitPosterior, read_posterior


def year_digests(flows: np.ndarray, noise: np.ndarray) -> list[str]:
    """SHA-256 per year of the observation row (NaN included) and its noise.

    Parameters
    ----------
    flows : ndarray, shape [n_y, n_out]
    noise : ndarray, shape [n_y] or [n_y, n_ch]
    """
    flows = np.atleast_2d(np.asarray(flows, float))
    noise = np.asarray(noise, float).reshape(len(flows), -1)
    return [hashlib.sha256(np.ascontiguousarray(f).tobytes()
                           + np.ascontiguousarray(n).tobytes()).hexdigest()
            for f, n in zip(flows, noise)]


def _config_difference(old: str, new: str) -> str:
    """The first config keys (dotted) whose values differ, for the error message."""
    a, b = yaml.safe_load(old) or {}, yaml.safe_load(new) or {}
    out = []

    def walk(x, y, where):
        if isinstance(x, dict) and isinstance(y, dict):
            for k in sorted(set(x) | set(y), key=str):
                walk(x.get(k), y.get(k), f"{where}.{k}" if where else str(k))
        elif x != y:
            out.append(f"{where} {x!r} -> {y!r}")
    walk(a, b, "")
    return "; ".join(out[:3]) + (" ..." if len(out) > 3 else "")


class Kept:
    """A unit whose result is already known (kept from the earlier posterior, or finished by
    the vectorised sampler), in ``calibrate()``'s table of runs."""

    done = True

    def __init__(self, posterior: UnitPosterior):
        self.posterior, self.years, self.k = posterior, posterior.years, len(posterior.years)

    @property
    def samples_from(self) -> int:
        """Years whose draws stay in the posterior it continues (its writer needs it)."""
        return self.posterior.samples_from

    def result(self) -> UnitPosterior:
        return self.posterior


def plan_update(cfg: Config, surrogate_id: str, output: str | os.PathLike,
                runs: dict, method: Method) -> tuple[dict[str, UnitPosterior], dict]:
    """Which units continue an earlier ``posterior.h5`` and from where.

    Parameters
    ----------
    cfg : Config
    surrogate_id : str
        Fingerprint of the surrogate of this run.
    output : path-like
        The posterior to update (also the one to write).
    runs : dict unit -> object with ``years``, ``flows``, ``noise``
        This run's units and their data.
    method : Method
        The method this run samples with (:func:`~twinmon.calibrate.resolve_method`): a unit
        with new years continues after its stored ones when it ``continues_years``, else it
        is sampled again in full.

    Returns
    -------
    resume : dict unit -> UnitPosterior
        Units that keep their stored years (their arrays as they are): all of the unit's
        years, or (sequential method) the first ones, sampling continuing after them, or
        (laplace method) the first ones' sites, the unit drawn again from them and the new
        years' (a posterior without sites: sampled again in full). With the joint method a
        unit with new years is sampled again in full. Their draws are left in the file
        (``samples_from``) unless it is a ``twinmon.posterior/1`` file.
    info : dict
        ``{"from", "kept_years", "new_years", "new_units", "redone_units", "dropped_units"}``
        for the summary (``from`` is None when there was no earlier posterior);
        ``new_years``: unit-years sampled (laplace: summarised), ``kept_years`` the others.

    Raises
    ------
    ArtifactError
        The posterior was made with another config or surrogate, or lacks the records an
        update needs.
    """
    path = Path(output)
    total = sum(len(r.years) for r in runs.values())
    if not path.exists():
        return {}, {"from": None, "kept_years": 0, "new_years": total,
                    "new_units": sorted(runs), "redone_units": [], "dropped_units": []}
    prov = artifacts.read_provenance(path)
    # The draws of the kept years stay in the file (write_posterior(base=...) appends to a
    # copy of it); a posterior/1 file is read whole and written again in the new layout.
    post = read_posterior(path, draws=prov.get("schema") != artifacts.schema_name("posterior"))
    artifacts.check_same_version(prov, path, "calibrate")
    want = cfg.section_yaml(*SECTIONS)
    if prov.get("config") != want:
        raise ArtifactError(f"{path}: made with another config ("
                            f"{_config_difference(prov.get('config', ''), want)}); "
                            "re-run calibrate without --update")
    if prov.get("surrogate_id", "") != surrogate_id:
        raise ArtifactError(f"{path}: made through another surrogate (surrogate_id "
                            f"{str(prov.get('surrogate_id', ''))[:12] or 'missing'}, this one "
                            f"{surrogate_id[:12]}); re-run calibrate without --update")
    stored = dict(post.units.each())        # one opening of the file for the whole fleet
    # ``calibrate.method: auto`` picks by the fleet's size, so the same config can pick
    # another method once units are added: the stored years cannot be continued then.
    was = prov.get("method") or ("joint" if any(p.trend for p in stored.values())
                                 else "sequential")
    if was != method.name:
        raise ArtifactError(f"{path}: sampled with the {was} method, this run uses the "
                            f"{method.name} method (calibrate.method {cfg.calibrate.method}, "
                            f"{len(runs)} units); re-run calibrate without --update")
    resume, new, redone = {}, [], []
    for unit, run in runs.items():
        if unit not in stored:
            new.append(unit)
            continue
        p = stored[unit]
        if not (np.size(p.digest) and np.size(p.var) and np.size(p.chain_end)):
            raise ArtifactError(f"{path}: /units/{unit} lacks the records an update continues "
                                "from (var, chain_end, digest: written by an older twinmon); "
                                "re-run calibrate without --update")
        n = len(p.years)
        years = np.asarray(run.years)
        same = n <= len(years) and np.array_equal(p.years, years[:n]) and \
            list(p.digest) == year_digests(run.flows, run.noise)[:n]
        if same and method.uses_events:
            # An event added or removed moves the trend's segments, whatever the years.
            now = [(int(e.year), str(e.component), str(e.action))
                   for e in getattr(run, "events", ())]
            same = [(int(y), str(c), str(a)) for y, c, a in p.events] == now
        if not same:
            redone.append(unit)
        elif n == len(years) or (method.continues_years and method.can_continue(p)):
            resume[unit] = p      # a joint history is one posterior: new years redo it all
    kept = sum(len(p.years) for p in resume.values())
    return resume, {"from": str(path), "kept_years": kept, "new_years": total - kept,
                    "new_units": new, "redone_units": redone,
                    "dropped_units": sorted(set(post.units) - set(runs))}
