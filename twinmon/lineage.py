"""Lineage: do the artifacts a command is given belong to one chain of runs?

Every artifact records the files it was made from (root attribute ``inputs``: a JSON list of
``{path, sha256}``; a posterior also records the fingerprint of its surrogate,
``surrogate_id``). A stage given several artifacts checks here that each was made from the
others it is given, so that a forecast of one posterior is never reported beside another
posterior, nor a posterior scored through a surrogate it was not calibrated with.

Only root attributes are read (and the SHA-256 of the files a link needs), so the check
costs little beside the stage's own reading. An artifact that records no inputs (made
before they were recorded) is not checked.
"""
from __future__ import annotations

import json
import os
from pathlib import Path
from typing import Mapping, Optional

import h5py

from . import artifacts
from .errors import ArtifactError

#: (consumer, producer): every ``consumer`` artifact records the ``producer`` it was made
#: from among its inputs. Roles are artifact kinds, plus ``observations``.
LINKS = (
    ("surrogate", "simulations"),
    ("posterior", "surrogate"),
    ("posterior", "observations"),
    ("forecast", "posterior"),
    ("forecast", "surrogate"),
    ("backtest", "posterior"),
    ("backtest", "surrogate"),
)

#: The stage that makes each role, for the message.
MADE_BY = {"simulations": "simulate", "surrogate": "reduce", "observations": "fabricate or "
           "import-csv", "posterior": "calibrate", "forecast": "forecast", "backtest":
           "backtest", "gap": "diagnose"}


def recorded_inputs(path: str | os.PathLike) -> list[dict]:
    """The ``inputs`` an artifact records (``[]`` when it records none).

    Raises
    ------
    ArtifactError
        The attribute is there but is not a JSON list of ``{path, sha256}`` (a damaged or
        edited file), or the file is not readable HDF5.
    """
    return _provenance(Path(path))["inputs"]


def _provenance(path: Path) -> dict:
    try:
        with h5py.File(path, "r") as f:
            attrs = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()
                     if k in ("inputs", "surrogate_id", "content_id", "config")}
    except OSError:
        raise ArtifactError(f"{path}: not a readable HDF5 file") from None
    text = attrs.get("inputs", "[]")
    try:
        records = json.loads(text) if isinstance(text, str) else None
    except json.JSONDecodeError:
        records = None
    if not isinstance(records, list) or not all(
            isinstance(r, dict) and isinstance(r.get("sha256"), str) for r in records):
        raise ArtifactError(f"{path}: attribute 'inputs' is not a JSON list of "
                            "{path, sha256} records (damaged or edited file)")
    attrs["inputs"] = records
    return attrs


def check_chain(given: Mapping[str, Optional[str | os.PathLike]]) -> None:
    """Refuse a set of artifacts that do not belong together.

    Parameters
    ----------
    given : mapping role -> path or None
        Roles as in :data:`LINKS` (``simulations``, ``surrogate``, ``observations``,
        ``posterior``, ``forecast``, ``backtest``); ``None`` and missing files are skipped
        (the stage's reader reports a missing file).

    Raises
    ------
    ArtifactError
        Naming both files: ``consumer`` was not made from ``producer``.
    """
    paths = {role: Path(p) for role, p in given.items()
             if p is not None and Path(p).is_file()}
    prov: dict[str, dict] = {}
    digest: dict[str, str] = {}

    def provenance(role: str) -> dict:
        if role not in prov:
            prov[role] = _provenance(paths[role])
        return prov[role]

    for consumer, producer in LINKS:
        if consumer not in paths or producer not in paths:
            continue
        made = provenance(consumer)
        if consumer == "posterior" and producer == "surrogate":
            # The surrogate's content, whatever file holds it (reduce re-run to the same
            # result): the fingerprint forecast checks as well.
            want, have = made.get("surrogate_id"), provenance(producer).get("content_id")
            if want and have:
                if want != have:
                    _refuse(paths, consumer, producer, "its surrogate fingerprint differs")
                continue
        records = made["inputs"]
        if not records:
            continue
        if producer not in digest:
            digest[producer] = artifacts.file_sha256(paths[producer])
        if digest[producer] not in {r["sha256"] for r in records}:
            _refuse(paths, consumer, producer,
                    f"sha256 {digest[producer][:12]} is not among its inputs")


def _refuse(paths: Mapping[str, Path], consumer: str, producer: str, why: str) -> None:
    raise ArtifactError(f"{paths[consumer]} was not made from {paths[producer]} ({why}): "
                        f"{consumer} and {producer} of different runs; pass the {producer} it "
                        f"was made from, or re-run {MADE_BY[consumer]}")


def check_made_for_model(path: str | os.PathLike, role: str, model_yaml: str) -> None:
    """Refuse an artifact made for another ``model`` section (another design box, other
    inputs) than the config's.

    Parameters
    ----------
    path : path-like
        The artifact (its ``config`` attribute is the YAML of the sections that made it).
    role : str
        What it is, for the message.
    model_yaml : str
        ``cfg.section_yaml("model")`` of the command's config.
    """
    import yaml
    recorded = _provenance(Path(path)).get("config") or ""
    try:
        theirs = (yaml.safe_load(recorded) or {}).get("model")
    except yaml.YAMLError:
        raise ArtifactError(f"{path}: attribute 'config' is not YAML (damaged or edited "
                            "file)") from None
    ours = (yaml.safe_load(model_yaml) or {}).get("model")
    if theirs is None or theirs == ours:
        return
    keys = sorted(k for k in set(theirs) | set(ours) if theirs.get(k) != ours.get(k))
    raise ArtifactError(f"{path}: {role} made for another model than the config's (model."
                        f"{keys[0] if keys else '?'} differs); re-run the stage that made it "
                        "with this config")
