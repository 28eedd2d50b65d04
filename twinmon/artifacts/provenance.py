"""Provenance: the root attributes every artifact carries (schema, version, time, config,
input hashes, seed), reading them back, and the up-to-date test of ``twinmon run``."""
from __future__ import annotations

import datetime as _dt
import hashlib
import json
import os
from pathlib import Path
from typing import Sequence

import h5py

from ..errors import ArtifactError
from .schema import schema_name


def file_sha256(path: str | os.PathLike) -> str:
    """SHA-256 of a file's bytes (hex)."""
    h = hashlib.sha256()
    with open(path, "rb") as fh:
        for block in iter(lambda: fh.read(1 << 20), b""):
            h.update(block)
    return h.hexdigest()


def input_records(paths: Sequence[str | os.PathLike]) -> list[dict]:
    """``[{path, sha256}]`` for the files a stage read, for provenance and up-to-date checks."""
    return [{"path": str(p), "sha256": file_sha256(p)} for p in paths]


def _version() -> str:
    from .. import __version__
    return __version__


def utc_now() -> str:
    """Current UTC time, ISO 8601 to the second."""
    return _dt.datetime.now(_dt.timezone.utc).isoformat(timespec="seconds")


def set_provenance(f: h5py.File, kind: str, *, config: str, records: list[dict],
                   seed: int | None) -> None:
    """Write the root attributes every artifact carries."""
    f.attrs["schema"] = schema_name(kind)
    f.attrs["twinmon_version"] = _version()
    f.attrs["created"] = utc_now()
    f.attrs["config"] = config
    f.attrs["inputs"] = json.dumps(records)
    if seed is not None:
        f.attrs["seed"] = int(seed)


def read_provenance(path: str | os.PathLike) -> dict:
    """The root attributes of an artifact as plain Python (any schema).

    Raises
    ------
    ArtifactError
        Not a readable HDF5 file (truncated, damaged), or ``inputs`` that is not JSON."""
    try:
        with h5py.File(path, "r") as f:
            out = {k: (v.decode() if isinstance(v, bytes) else v) for k, v in f.attrs.items()}
    except FileNotFoundError:
        raise ArtifactError(f"{path}: file not found") from None
    except OSError as exc:
        what = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise ArtifactError(f"{path}: not a readable HDF5 file ({what}); re-run the stage "
                            "that made it") from None
    if "inputs" in out:
        try:
            out["inputs"] = json.loads(out["inputs"])
        except (json.JSONDecodeError, TypeError):
            raise ArtifactError(f"{path}: attribute 'inputs' is not JSON (damaged or edited "
                                "file); re-run the stage that made it") from None
        if not isinstance(out["inputs"], list) or not all(
                isinstance(r, dict) and "sha256" in r for r in out["inputs"]):
            raise ArtifactError(f"{path}: attribute 'inputs' is not a list of {{path, sha256}} "
                                "records (damaged or edited file)")
    return out


def check_same_version(prov: dict, path: str | os.PathLike, stage: str) -> None:
    """Refuse (:class:`ArtifactError`) to continue an artifact another twinmon made.

    ``--update`` keeps what an earlier run computed (a posterior's years, a gap's per-year
    fits) and recomputes the rest: with another version the two halves may come from
    different code (another fit tolerance, another sampler), and the result would be neither
    version's full run. ``prov``: :func:`read_provenance` of ``path``; ``stage``: the
    command to run again without ``--update``."""
    made = prov.get("twinmon_version")
    if made != _version():
        raise ArtifactError(f"{path}: made by twinmon {made or 'of unknown version'}, this is "
                            f"twinmon {_version()}; an update continues only its own "
                            f"version's results: re-run {stage} without --update")


def is_up_to_date(output: str | os.PathLike, kind: str, config: str,
                  inputs: Sequence[str | os.PathLike]) -> bool:
    """True when ``output`` exists, has the right schema, was made by this version of
    twinmon from the same config section and from inputs with the same hashes. Used by
    ``twinmon run`` to skip stages: an artifact of another version is made again, since
    what a stage computes may have changed with it."""
    output = Path(output)
    if not output.exists():
        return False
    if not _readable_hdf5(output):
        return False                    # damaged: the stage makes it again
    prov = read_provenance(output)
    if prov.get("schema") != schema_name(kind) or prov.get("config") != config \
            or prov.get("twinmon_version") != _version():
        return False
    try:
        want = input_records(inputs)
    except OSError:
        return False
    return [r["sha256"] for r in prov.get("inputs", [])] == [r["sha256"] for r in want]


def _readable_hdf5(path: Path) -> bool:
    try:
        with h5py.File(path, "r"):
            return True
    except OSError:
        return False
