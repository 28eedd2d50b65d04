"""``diagnose --update``: diagnose again with the years added since an earlier ``gap.h5``.

Most of a unit's diagnosis is per year: the base fit of year ``k`` (maximum likelihood through
the FMU, warm-started from year ``k - 1``'s fit) depends only on years ``<= k``, and the
initial screening's chi-square gain of each candidate at year ``k`` (``gains[:, k]``) only on
year ``k``'s base fit. On a unit without a gap these are 87 % of its time (30 units, -j 1:
base fit 4.3 s and screening 11.6 s of 18.2 s). ``gap.h5`` keeps them per unit-year
(:class:`YearCache`, under ``/units/<U>/cache``), so that an update fits and screens only
the new years; the rest of the diagnosis -- the tests over all years, the confirmation fits
(joint over years), the shrink, the residual maps and predictions -- is computed again as in
a full run. The FMU is deterministic, so the result equals a full run's, array for array
(``tests/unit/test_diagnose_update.py``).

A unit is diagnosed in full instead when it is new, when the data of a stored year changed
(each year's whitened observation row and its noise are recorded as a SHA-256 by
:func:`~twinmon.calibrate.update.year_digests`: a corrected file, or a noise estimated from
all the unit's years, which moves when years are added), or when its stored years are not
the first of its years now (a year inserted or removed). Units no longer in the observations
are left out, as a full run would. An update is refused (``ArtifactError``) when ``gap.h5``
was made by another version of twinmon, with another ``model``/``diagnose``/``safety``
config, through another FMU (its SHA-256), or before these records existed.

What an updated unit reports of its own cost: ``fmu_runs`` and ``wall_time`` are those of
this run (the new years' base fit and screening plus everything recomputed), not the
cumulated cost of the kept years; they are the only values that differ from a full run.
"""
from __future__ import annotations

import json
import os
from dataclasses import dataclass
from pathlib import Path

import h5py
import numpy as np

from .. import artifacts
from ..calibrate.update import _config_difference, year_digests
from ..config import Config
from ..errors import ArtifactError

#: Datasets of a unit's per-year records in ``gap.h5`` (see :func:`write_cache`).
CACHE, CACHE_GAINS = "cache", "cache_gains"

#: Compression of the cache datasets (a unit-year of the pump: 25 samples x 2 inputs).
_GZIP = {"compression": "gzip", "compression_opts": 4, "shuffle": True}


@dataclass
class YearCache:
    """What a unit's diagnosis computed year by year, kept in ``gap.h5`` for ``--update``.

    Rows are stored on the full sample grid of the whitened observations (``m = n_ch * n_t``,
    channel-major), NaN where the sample is missing; a year's fitted rows are its finite ones.

    Attributes
    ----------
    digest : list of str, [n_y]
        SHA-256 of each year's whitened observation row and its noise per channel.
    base_u : ndarray, shape [n_y, d]
        Normalised degradation inputs of the base fit.
    base_rows : ndarray, shape [n_y, m]
        Whitened residual of the base fit.
    base_jac : ndarray, shape [n_y, m, d]
        Its Jacobian w.r.t. the normalised inputs.
    base_lev : ndarray, shape [n_y, m]
        Leverage of each sample.
    screen_gains : dict of str to ndarray, each [n_v, n_y]
        Initial screening's chi-square gain per candidate, grid value and year.
    """

    digest: list
    base_u: np.ndarray
    base_rows: np.ndarray
    base_jac: np.ndarray
    base_lev: np.ndarray
    screen_gains: dict

    @property
    def n_years(self) -> int:
        return len(self.digest)

    @classmethod
    def of(cls, s, screened: dict) -> "YearCache":
        """The records of a diagnosed unit: its state ``s`` after step 1 and the initial
        screening ``{candidate: (score, value, onset, gains [n_v, n_y])}``."""
        rows = np.full((s.n_y, s.m), np.nan)
        jac = np.full((s.n_y, s.m, s.d), np.nan)
        lev = np.full((s.n_y, s.m), np.nan)
        for k in range(s.n_y):
            mask = np.isfinite(s.Y[k])
            rows[k, mask], jac[k, mask], lev[k, mask] = s.base_rows[k], s.base_J[k], s.base_lev[k]
        return cls(unit_digests(s.Y, s.twin.sigma[::s.n_t]), s.base_u.copy(), rows, jac, lev,
                   {c: np.asarray(v[3]) for c, v in screened.items()})

    def year(self, k: int, mask: np.ndarray) -> tuple:
        """Year ``k``'s ``(u [d], row [n_k], J [n_k, d], leverage [n_k])`` on the samples
        ``mask`` [m] (its finite observations)."""
        return (self.base_u[k].copy(), self.base_rows[k][mask], self.base_jac[k][mask],
                self.base_lev[k][mask])


def unit_digests(Y: np.ndarray, sigma: np.ndarray) -> list:
    """Per-year SHA-256 of the whitened rows ``Y`` [n_y, m] and the noise per channel
    ``sigma`` [n_ch] (channel units)."""
    Y = np.asarray(Y, float)
    return year_digests(Y, np.tile(np.asarray(sigma, float), (len(Y), 1)))


def write_cache(grp: h5py.Group, c: YearCache) -> None:
    """A unit's records, in two datasets: ``cache`` [n_y] (compound, one row per year:
    ``digest``, ``base_u`` [d], ``base_rows`` [m], ``base_jac`` [m, d], ``base_lev`` [m])
    and ``cache_gains`` [n_c, n_v, n_y] (NaN past a candidate's grid; attribute ``grid``,
    JSON ``{"candidates": [...], "grid_sizes": [...]}``, gives each row's candidate and grid
    length). Two datasets per unit, not six: a 1000-unit gap.h5 writes and reads in a
    fraction of the time."""
    n_y = c.n_years
    m, d = np.shape(c.base_jac)[1:] if n_y else (0, np.shape(c.base_u)[-1])
    rec = np.zeros(n_y, cache_dtype(d, m))
    rec["digest"] = [str(v).encode() for v in c.digest]
    rec["base_u"], rec["base_rows"] = c.base_u, c.base_rows
    rec["base_jac"], rec["base_lev"] = c.base_jac, c.base_lev
    names = list(c.screen_gains)
    n_v = max((np.shape(x)[0] for x in c.screen_gains.values()), default=0)
    gains = np.full((len(names), n_v, n_y), np.nan)
    for i, x in enumerate(c.screen_gains.values()):
        gains[i, :np.shape(x)[0]] = x
    # An empty dataset (a unit of 0 years) cannot be chunked.
    grp.create_dataset(CACHE, data=rec, **(_GZIP if n_y else {}))
    ds = grp.create_dataset(CACHE_GAINS, data=gains, **(_GZIP if gains.size else {}))
    ds.attrs["grid"] = artifacts.json_attr(
        {"candidates": names, "grid_sizes": [int(np.shape(x)[0])
                                             for x in c.screen_gains.values()]})


def cache_dtype(d: int, m: int) -> np.dtype:
    """The row of ``/units/<U>/cache``: a year's digest and base fit (``d`` inputs, ``m``
    whitened samples)."""
    return np.dtype([("digest", "S64"), ("base_u", "<f8", (d,)), ("base_rows", "<f8", (m,)),
                     ("base_jac", "<f8", (m, d)), ("base_lev", "<f8", (m,))])


def read_cache(grp: h5py.Group, path) -> YearCache | None:
    """A unit's :class:`YearCache`, None if its group has none (a gap.h5 written before)."""
    if CACHE not in grp:
        return None
    if isinstance(grp[CACHE], h5py.Group):        # gap/1 (never released): not continued
        return None
    rec = artifacts.get(grp, CACHE, path)
    gains = artifacts.get(grp, CACHE_GAINS, path)
    grid = json.loads(grp[CACHE_GAINS].attrs["grid"])
    per = {n: x[:size] for n, x, size in zip(grid["candidates"], gains, grid["grid_sizes"])}
    return YearCache([v.decode() for v in rec["digest"]],
                     *(np.ascontiguousarray(rec[k])
                       for k in ("base_u", "base_rows", "base_jac", "base_lev")), per)


def check_update(cfg: Config, fmu, output: str | os.PathLike, sections) -> None:
    """Refuse (``ArtifactError``) to update ``output`` when it was made by another twinmon,
    with another config (``sections``) or another FMU than ``fmu``."""
    path = Path(output)
    prov = artifacts.read_provenance(path)
    if prov.get("schema") != artifacts.schema_name("gap"):
        old = prov.get("schema") in {f"twinmon.gap/{v}" for v in artifacts.READABLE["gap"]}
        raise ArtifactError(
            f"{path}: " + ("written by an older twinmon, without the per-year records an "
                           f"update continues from (schema {prov.get('schema')!r})"
                           if old else f"not a gap artifact (schema {prov.get('schema')!r}, "
                           f"expected {artifacts.schema_name('gap')!r})")
            + "; re-run diagnose without --update")
    artifacts.check_same_version(prov, path, "diagnose")
    want = cfg.section_yaml(*sections)
    if prov.get("config") != want:
        raise ArtifactError(f"{path}: made with another config ("
                            f"{_config_difference(prov.get('config', ''), want)}); "
                            "re-run diagnose without --update")
    # write_gap records its inputs as [observations, FMU, (posterior)].
    inputs = prov.get("inputs") or []
    old = inputs[1]["sha256"] if len(inputs) > 1 else ""
    new = artifacts.file_sha256(fmu)
    if old != new:
        raise ArtifactError(f"{path}: made through another FMU (sha256 {old[:12] or 'missing'}"
                            f", {fmu} is {new[:12]}); re-run diagnose without --update")


def plan_update(cfg: Config, fmu, output: str | os.PathLike, units: dict,
                sections) -> tuple[dict, dict]:
    """Which units continue from the per-year records of an earlier ``gap.h5``.

    Parameters
    ----------
    cfg : Config
    fmu : path-like
        The FMU of this run.
    output : path-like
        The ``gap.h5`` to update (also the one to write).
    units : dict of str to (ndarray [n_y], list of str [n_y])
        This run's units: their years and :func:`unit_digests`.
    sections : sequence of str
        Config sections recorded in ``gap.h5``.

    Returns
    -------
    kept : dict of str to YearCache
        The units continued, with their stored records (every stored year: they are the
        first of the unit's years now, with the same digests).
    info : dict
        ``{"from", "kept_years", "new_years", "new_units", "redone_units",
        "dropped_units"}`` for the summary (``from`` is None without an earlier gap.h5).

    Raises
    ------
    ArtifactError
        ``gap.h5`` was made with another config or FMU, or lacks the per-year records.
    """
    path = Path(output)
    total = sum(len(y) for y, _ in units.values())
    if not path.exists():
        return {}, {"from": None, "kept_years": 0, "new_years": total,
                    "new_units": sorted(units), "redone_units": [], "dropped_units": []}
    check_update(cfg, fmu, path, sections)
    kept, new, redone, stored = {}, [], [], []
    with artifacts.open_artifact(path, "gap") as f:
        grp = f["units"] if "units" in f else {}
        stored = list(grp)
        for unit in stored:
            if CACHE not in grp[unit]:
                raise ArtifactError(f"{path}: /units/{unit} lacks the per-year records an "
                                    f"update continues from (/units/{unit}/{CACHE}: written by "
                                    "an older twinmon); re-run diagnose without --update")
        for unit, (years, digests) in units.items():
            if unit not in grp:
                new.append(unit)
                continue
            c = read_cache(grp[unit], path)
            old_years = artifacts.get(grp[unit], "record", path)["years"]
            n = len(old_years)
            years = np.asarray(years)
            if n <= len(years) and np.array_equal(old_years, years[:n]) \
                    and c.n_years == n and list(c.digest) == list(digests[:n]):
                kept[unit] = c
            else:
                redone.append(unit)
    n_kept = sum(c.n_years for c in kept.values())
    return kept, {"from": str(path), "kept_years": n_kept, "new_years": total - n_kept,
                  "new_units": new, "redone_units": redone,
                  "dropped_units": sorted(set(stored) - set(units))}
