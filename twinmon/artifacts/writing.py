"""Writing artifacts: the atomic write (temporary file renamed into place under the output's
lock), datasets with units, JSON attributes, and the refusal of an output that is an input."""
from __future__ import annotations

import contextlib
import json
import os
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Iterator, Sequence

import h5py
import numpy as np

from ..errors import UsageError
from .locks import output_lock
from .provenance import input_records, set_provenance
from .reading import verify_artifact
from .temporaries import remove_stale_temporaries


#: Lowest HDF5 file-format version of the fleet-sized artifacts (``write_artifact(compact=True)``):
#: HDF5 >= 1.10 indexes a one-chunk dataset without a B-tree (about 2.3 kB less per dataset,
#: a quarter of a unit's posterior) and is read by every h5py of the last years.
COMPACT_LIBVER = ("v110", "v110")


@contextlib.contextmanager
def write_artifact(path: str | os.PathLike, kind: str, *, config: str = "",
                   inputs: Sequence[str | os.PathLike] = (), seed: int | None = None,
                   extra_attrs: dict | None = None,
                   compact: bool = False,
                   base: str | os.PathLike | None = None) -> Iterator[h5py.File]:
    """Open a temporary HDF5 file for writing an artifact; rename it into place on success.

    Parameters
    ----------
    path : path-like
        Final artifact path. Its folder is created if needed.
    kind : str
        Artifact kind, a key of :data:`SCHEMAS`.
    config : str
        The resolved YAML of the config sections that made it.
    inputs : sequence of path-like
        Files the stage read; their SHA-256 is recorded.
    seed : int, optional
        Seed of the randomness used, if any.
    compact : bool
        Write the HDF5 >= 1.10 file format (:data:`COMPACT_LIBVER`): smaller per-dataset
        metadata, for artifacts with many small datasets per unit.
    base : path-like, optional
        An artifact of the same kind to start from: the temporary file is a copy of it
        (opened read-write, its provenance replaced), so that a stage adding to a large
        artifact writes only what changed (``calibrate --update``). The copy is made under
        the output's lock; ``base`` may be ``path`` itself.

    Yields
    ------
    h5py.File
        The open temporary file. If the body raises, the temporary file is removed and the
        existing artifact at ``path`` (if any) is left untouched.
    """
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    records = input_records(inputs)  # hash before writing: an input may be overwritten
    with output_lock(path, f"twinmon ({kind})"):
        remove_stale_temporaries(path)
        tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
        try:
            if base is not None:
                import shutil
                verify_artifact(base, kind)
                shutil.copyfile(base, tmp)
            mode = "r+" if base is not None else "w"
            with h5py.File(tmp, mode, **({"libver": COMPACT_LIBVER} if compact else {})) as f:
                set_provenance(f, kind, config=config, records=records, seed=seed)
                for key, value in (extra_attrs or {}).items():
                    f.attrs[key] = value
                yield f
            os.replace(tmp, path)
        except OSError as exc:
            # Name the artifact, not the hidden temporary file, and keep HDF5's multi-line
            # internals out of the message.
            reason = exc.strerror or str(exc).splitlines()[0]
            raise OSError(exc.errno, f"cannot write: {reason}", str(path)) from None
        finally:
            if tmp.exists():
                tmp.unlink()


def same_file(a: str | os.PathLike, b: str | os.PathLike) -> bool:
    """True when two paths name one file: the same inode when both exist (a symlink, a hard
    link, ``./x`` and ``x``), the same resolved path otherwise."""
    try:
        return os.path.samefile(a, b)
    except OSError:
        return Path(a).resolve() == Path(b).resolve()


def check_outputs_not_inputs(outputs: Mapping[str, Any], inputs: Mapping[str, Any]) -> None:
    """Refuse a command line whose output is one of its inputs (or two outputs that are one
    file), before anything is read or written.

    Parameters
    ----------
    outputs, inputs : mapping option name -> path or None
        The command's options as the user would write them (``"-o"``, ``"--observations"``);
        ``None`` values are skipped.

    Raises
    ------
    UsageError
        Naming both options and the path: writing the output would overwrite the input.
    """
    outs = [(k, v) for k, v in outputs.items() if v is not None]
    ins = [(k, v) for k, v in inputs.items() if v is not None]
    for i, (name, out) in enumerate(outs):
        for other, src in ins + outs[i + 1:]:
            if same_file(out, src):
                raise UsageError(f"{out}: {name} is also {other}; writing it would overwrite "
                                 "what the command reads: choose another output")


def put(group: h5py.Group, name: str, data: Any, units: str, description: str,
        **kwargs) -> h5py.Dataset:
    """Create a dataset with its ``units`` and ``description`` attributes."""
    if isinstance(data, (list, tuple)) and data and isinstance(data[0], str):
        data = np.array(data, dtype=h5py.string_dtype())
    arr = np.asarray(data) if not isinstance(data, np.ndarray) else data
    if arr.ndim >= 1 and arr.size and arr.dtype.kind in "fiub":
        # A checksum per chunk: bytes flipped on disk are found on reading (an OSError that
        # open_artifact's reader reports as a damaged artifact) instead of being read as
        # plausible numbers.
        kwargs.setdefault("fletcher32", True)
    ds = group.create_dataset(name, data=data, **kwargs)
    ds.attrs["units"] = units
    ds.attrs["description"] = description
    return ds


def json_attr(obj: Any) -> str:
    """JSON text for an attribute (numpy scalars and arrays made plain)."""
    return json.dumps(obj, default=_plain)


def _plain(o: Any) -> Any:
    if isinstance(o, np.ndarray):
        return o.tolist()
    if isinstance(o, np.generic):
        return o.item()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON-able: {type(o).__name__}")
