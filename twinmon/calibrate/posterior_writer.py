"""Writing ``posterior.h5``: :class:`PosteriorWriter` (unit by unit, as calibrate finishes
them) and :func:`write_posterior` (a whole fleet at once); the layout is read back by
:func:`~twinmon.calibrate.posterior.read_posterior`."""
from __future__ import annotations

import json
import os

import h5py
import numpy as np

from .. import artifacts
from ..config import Config
from ..errors import ArtifactError
from .fit import FIT_FIELDS
from .posterior import (DRAW_DTYPE, RECORD_FIELDS, SECTIONS, SEED_OFFSET, SITE_FIELDS,
                        UnitPosterior, record_dtype, thin_indices)
from .trend import TREND_DRAWS, TREND_FIELDS


def _records(p: UnitPosterior) -> np.ndarray:
    """A unit's per-year results as one structured array [n_y] (:func:`record_dtype`)."""
    n_y, d = np.shape(p.mean)
    cont = bool(np.size(p.var) and np.size(p.chain_end) and np.size(p.digest))
    n_ch = np.shape(p.fit["channel_rms"])[1] if p.fit and "channel_rms" in p.fit else 0
    n_site = np.shape(p.site["var"])[1] if p.site else 0
    rec = np.zeros(n_y, record_dtype(d, p.chains, n_ch, bool(p.fit), cont, n_site))
    rec["year"] = p.years
    for k in ("mean", "median", "q05", "q95", "rhat", "ess"):
        rec[k] = getattr(p, k)
    rec["acceptance"], rec["noise_std"] = p.acceptance, p.noise_std
    rec["surrogate_var_ratio"] = p.surrogate_var_ratio if np.size(p.surrogate_var_ratio) \
        else np.nan
    if cont:
        rec["var"], rec["chain_end"] = p.var, p.chain_end
        rec["digest"] = [str(v).encode() for v in p.digest]
    for key in FIT_FIELDS if p.fit else ():
        v = np.asarray(p.fit[key])
        rec[f"fit_{key}"] = [str(x).encode() for x in v] if key == "status" else v
    if n_ch:
        rec["fit_channel_rms"] = p.fit["channel_rms"]
    for key in SITE_FIELDS if n_site else ():
        rec[f"site_{key}"] = p.site[key]
    return rec


def write_posterior(path, posterior: dict[str, UnitPosterior], input_names: list[str],
                    cfg: Config, inputs, surrogate_id: str = "",
                    base: str | os.PathLike | None = None, method: str = "") -> None:
    """Write ``posterior.h5`` atomically: every unit of ``posterior`` through one
    :class:`PosteriorWriter` (its parameters and the layout); a unit it refuses leaves
    nothing written."""
    with PosteriorWriter(path, input_names, cfg, inputs, surrogate_id, base, method) as w:
        for unit, p in posterior.items():
            w.add(unit, p)


class PosteriorWriter:
    """``posterior.h5`` written unit by unit, renamed into place when the ``with`` block
    ends without an error (a failed or interrupted calibration leaves the earlier file as
    it was). Calibrate adds each unit as the sampler finishes it, so a fleet's draws never
    sit in memory whole.

    A unit is two datasets: its per-year results as one compound ``record`` [n_y]
    (:func:`record_dtype`; a fleet of 1000 units writes and reads in about a tenth of the
    time of two dozen small datasets per unit) and its draws. The summary statistics (mean,
    quantiles, R-hat, ESS) are those of all the draws, as computed by calibration; only
    ``calibrate.keep_draws`` draws per year are stored, evenly thinned (:func:`thin_indices`),
    one gzip-compressed chunk per unit-year. The draws' ``draws_total`` attribute records the
    thinning. Both datasets can grow along the years.

    Parameters
    ----------
    path : path-like
    input_names : list of str
    cfg : Config
    inputs : list of path-like
        The files the posterior was made from (their hashes are its provenance).
    surrogate_id : str
        The :meth:`~twinmon.reduce.Surrogate.fingerprint` of the surrogate the posterior
        was sampled through.
    base : path-like, optional
        The ``twinmon.posterior/2`` file that ``calibrate --update`` continues. The new file
        starts as its copy; a unit with ``samples_from > 0`` keeps the draws of its first
        ``samples_from`` years there (they are neither read nor compressed again) and gets
        its record rewritten and its new years' draws appended; other units are written
        afresh, and units of ``base`` not added are removed at the end.
    method : str
        The method the units were sampled with (what ``calibrate.method: auto`` resolved
        to).
    """

    def __init__(self, path, input_names: list[str], cfg: Config, inputs,
                 surrogate_id: str = "", base: str | os.PathLike | None = None,
                 method: str = ""):
        self.path, self.cfg, self.base = path, cfg, base
        self.keep = cfg.calibrate.keep_draws
        self._ctx = artifacts.write_artifact(path, "posterior",
                                             config=cfg.section_yaml(*SECTIONS),
                                             inputs=inputs, seed=cfg.seed + SEED_OFFSET,
                                             compact=True, base=base)
        self._head = (list(input_names), surrogate_id, method)
        self.written: set[str] = set()
        self._channels: dict[str, None] = {}

    def __enter__(self) -> "PosteriorWriter":
        f = self.f = self._ctx.__enter__()
        names, surrogate_id, method = self._head
        cfg = self.cfg
        if surrogate_id:
            f.attrs["surrogate_id"] = surrogate_id
        if method:
            f.attrs["method"] = method
        f.attrs["input_names"] = json.dumps(names)
        f.attrs["input_units"] = json.dumps([cfg.model.inputs[n].units for n in names])
        out_units = cfg.model.output.units
        f.attrs["record_fields"] = json.dumps(
            {k: [out_units if u == "output units" else u, desc]
             for k, (u, desc) in RECORD_FIELDS.items()})
        f.attrs["samples_description"] = _SAMPLES_DOC
        f.attrs["fit_windows"] = json.dumps(list(cfg.diagnose_windows()))
        self.units = f.require_group("units")
        return self

    def add(self, unit: str, p: UnitPosterior) -> None:
        """Write one unit (again: a unit of ``base`` is replaced, or appended to when
        ``p.samples_from > 0``)."""
        if p.samples_from and self.base is None:
            raise ValueError("a posterior whose draws are partly in another file needs base=")
        if unit in self.written:
            raise ValueError(f"unit {unit!r} written twice")
        if len(p.years) > p.samples_from and np.shape(p.samples)[1] == 0:
            raise ValueError(f"unit {unit!r} has no draws (a calibrate summary keeps only "
                             "the statistics: write the posterior read from its file)")
        if p.samples_from:
            _append_unit(self.units[unit], p, self.keep)
        else:
            if unit in self.units:
                del self.units[unit]
            _write_unit(self.units.create_group(unit), p, self.keep)
        self.written.add(unit)
        self._channels.update(dict.fromkeys(p.channels))

    def __exit__(self, *exc) -> bool:
        if exc[0] is None:
            try:
                for unit in set(self.units) - self.written:
                    del self.units[unit]   # no longer observed: a full run would not have it
                self.f.attrs["channels"] = json.dumps(list(self._channels)
                                                      or [self.cfg.model.output.name])
            except BaseException as e:     # the temporary file goes, the lock is released
                self._ctx.__exit__(type(e), e, e.__traceback__)
                raise
        return bool(self._ctx.__exit__(*exc))


#: Rows per chunk of a unit's record: one chunk holds 16 years (a record row is 0.3-0.6 kB).
RECORD_CHUNK = 16


def _write_unit(g: h5py.Group, p: UnitPosterior, keep: int) -> None:
    """A unit's record, draws and attributes, into its new group ``g``."""
    # fletcher32: flipped bytes are found on reading, as in every other dataset.
    g.create_dataset("record", data=_records(p), chunks=(RECORD_CHUNK,), maxshape=(None,),
                     fletcher32=True)
    _put_draws(g, np.asarray(p.samples), keep)
    _unit_attrs(g, p)
    if p.trend:         # the joint method's trend posterior
        _put_trend(g, p.trend, keep)


def _unit_attrs(g: h5py.Group, p: UnitPosterior) -> None:
    g.attrs["noise_source"] = p.noise_source
    for key, value in (("events", json.dumps([[int(y), str(c), str(a)]
                                              for y, c, a in p.events]) if p.events else None),
                       ("channels", artifacts.json_attr(p.channels) if p.channels else None),
                       ("found_repairs", artifacts.json_attr(p.found_repairs)
                        if p.found_repairs else None)):
        if value is not None:
            g.attrs[key] = value
        elif key in g.attrs:
            del g.attrs[key]


def _append_unit(g: h5py.Group, p: UnitPosterior, keep: int) -> None:
    """A continued unit: its record rewritten whole (a few hundred bytes a year) and the
    draws of its years from ``p.samples_from`` on appended; the earlier draws stay as they
    are in the file.

    Through h5py's low-level calls: the high-level ones convert the record's compound type
    to numpy at every access (3.8 s of writing 1000 units, profiled, against 1.5 s)."""
    from h5py import h5s
    rec = _records(p)
    ds = g["record"].id
    if not ds.get_type().equal(artifacts.file_type(rec.dtype)):
        raise ArtifactError(f"{g.file.filename}: {g.name}/record has other fields than this "
                            "run's; re-run calibrate without --update")
    ds.set_extent((len(rec),))
    ds.write(h5s.ALL, h5s.ALL, rec)
    draws = g["samples"].id
    new = np.asarray(p.samples)
    # Rounded as a full run stores them, whatever type an older file's dataset has.
    new = np.ascontiguousarray(new[:, thin_indices(new.shape[1], keep), :], DRAW_DTYPE)
    if draws.shape[0] != p.samples_from or draws.shape[1:] != new.shape[1:]:
        raise ArtifactError(f"{g.file.filename}: {g.name}/samples has shape {draws.shape}, "
                            f"expected ({p.samples_from}, {new.shape[1]}, {new.shape[2]}); "
                            "re-run calibrate without --update")
    if len(new):
        draws.set_extent((len(rec),) + new.shape[1:])
        space = draws.get_space()
        space.select_hyperslab((p.samples_from, 0, 0), new.shape)
        draws.write(h5s.create_simple(new.shape), space, new)
    _unit_attrs(g, p)


_SAMPLES_DOC = ("/units/<U>/samples [year, draw, input], input units: post-burn-in MCMC "
                "draws evenly thinned over the chain-major pooled draws to "
                "calibrate.keep_draws (its draws_total attribute: the draws before thinning); "
                "the record's statistics are of all the draws")


def _put_trend(g: h5py.Group, trend: dict, keep: int) -> None:
    """``/units/<U>/trend/<field>`` (``trend.TREND_FIELDS``); the draws thinned like the
    years' (:func:`thin_indices`), their diagnostics of all the draws."""
    for key, (units, desc) in TREND_FIELDS.items():
        if key not in trend:        # an optional field (TREND_OPTIONAL)
            continue
        data = np.asarray(trend[key])
        if key in TREND_DRAWS:
            data = data[thin_indices(len(data), keep)]
            if key in ("shape", "change_year", "change_years"):
                data = data.astype(np.int16)        # codes and years
            elif data.dtype.kind == "f":
                data = data.astype(DRAW_DTYPE)
            if data.size:
                # Shuffle + gzip, as the years' draws: the shapes' fields are mostly zeros
                # and repeats (benchmarks/fleet_scale.py: 136 -> 72 kB of trend a unit).
                artifacts.put(g, f"trend/{key}", data, units, desc, compression="gzip",
                              compression_opts=4, shuffle=True)
                continue
        artifacts.put(g, f"trend/{key}", data, units, desc)


def _put_draws(g: h5py.Group, samples: np.ndarray, keep: int) -> None:
    """The thinned draws [n_y, n_kept, d] as :data:`DRAW_DTYPE`: one chunk per year, so
    reading a unit-year reads one chunk; shuffle + gzip shrink them a little further."""
    n_y, n_draws, d = samples.shape
    kept = samples[:, thin_indices(n_draws, keep), :].astype(DRAW_DTYPE)
    chunks = (1, kept.shape[1], d) if kept.size else None
    ds = g.create_dataset("samples", data=kept, chunks=chunks,
                          maxshape=(None,) + kept.shape[1:] if kept.size else None,
                          compression="gzip" if kept.size else None,
                          compression_opts=4 if kept.size else None, shuffle=bool(kept.size),
                          fletcher32=bool(kept.size))
    ds.attrs["draws_total"] = n_draws
