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
    with output_lock(path, f"twinmon ({kind})"), replacing(path) as tmp:
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
        from ..interrupts import raise_if_interrupted
        raise_if_interrupted()      # a Ctrl-C swallowed while writing: not made final


@contextlib.contextmanager
def replacing(path: Path) -> Iterator[Path]:
    """A temporary file beside ``path`` (yielded; stale ones from killed runs removed
    first), renamed over ``path`` when the block ends normally and removed otherwise, so
    that ``path`` is either the old file or the whole new one. Call it under
    :func:`~.locks.output_lock`. An ``OSError`` names ``path``, not the hidden temporary
    file, in one line (HDF5's multi-line internals kept out)."""
    remove_stale_temporaries(path)
    tmp = path.with_name(f".{path.name}.{os.getpid()}.tmp")
    try:
        yield tmp
        os.replace(tmp, path)
    except OSError as exc:
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
        if kwargs == {"fletcher32": True} and "/" not in name:
            dsid = _new_checked(group, name, arr)
            set_attrs(dsid, {"units": units, "description": description})
            return h5py.Dataset(dsid)
    ds = group.create_dataset(name, data=data, **kwargs)
    set_attrs(ds, {"units": units, "description": description})
    return ds


def _new_checked(group: h5py.Group, name: str, arr: np.ndarray):
    """What ``group.create_dataset(name, data=arr, fletcher32=True)`` makes (the same
    chunks, filters and type), through the low-level API with the creation properties
    kept per shape and type: a fleet's artifacts hold tens of thousands of small datasets,
    and h5py's high-level path rebuilt them each time (half of a forecast unit's 9 ms
    write)."""
    from h5py import h5d, h5p, h5s
    from h5py._hl import filters
    arr = np.ascontiguousarray(arr)
    key = (arr.shape, arr.dtype.str)
    made = _CHECKED_DCPL.get(key)
    if made is None:
        dcpl = filters.fill_dcpl(h5p.create(h5p.DATASET_CREATE), arr.shape, arr.dtype,
                                 None, None, None, None, True, None, None, None)
        dcpl.set_obj_track_times(False)
        if h5py.get_config().track_order:
            dcpl.set_attr_creation_order(h5p.CRT_ORDER_TRACKED | h5p.CRT_ORDER_INDEXED)
        if len(_CHECKED_DCPL) >= _KEPT_TYPES:
            _CHECKED_DCPL.clear()
        made = _CHECKED_DCPL[key] = (dcpl, _types(arr.dtype))
    dcpl, (file_type, mem_type) = made
    dsid = h5d.create(group.id, name.encode(), file_type, h5s.create_simple(arr.shape),
                      dcpl=dcpl)
    dsid.write(h5s.ALL, h5s.ALL, arr, mtype=mem_type)
    return dsid


def set_attrs(obj, values: Mapping[str, Any]) -> None:
    """``obj.attrs[name] = value`` for each item: the same types and bytes, through the
    low-level API for strings, numbers and numeric arrays (h5py's high-level path builds
    both HDF5 types on every call: about 60 of its 90 us, tens of thousands of times for a
    fleet), h5py's own for anything else. ``obj``: a group, a dataset or their low-level
    identifier."""
    from h5py import h5a, h5d, h5s
    oid = obj.id if hasattr(obj, "attrs") else obj
    for name, value in values.items():
        if isinstance(value, str):
            data = np.array(value, dtype=_STR)
        elif isinstance(value, (bool, int, float, np.number, np.bool_)) or (
                isinstance(value, np.ndarray) and value.dtype.kind in "fiub"):
            # (np.ascontiguousarray would make a scalar an array of one.)
            data = np.asarray(value, order="C")
        else:
            owner = obj if hasattr(obj, "attrs") else (
                h5py.Dataset(oid) if isinstance(oid, h5d.DatasetID) else h5py.Group(oid))
            owner.attrs[name] = value
            continue
        file_type, mem_type = _types(data.dtype)
        key = name.encode()
        if h5a.exists(oid, key):
            h5a.delete(oid, key)
        space = h5s.create(h5s.SCALAR) if data.ndim == 0 else h5s.create_simple(data.shape)
        attr = h5a.create(oid, key, file_type, space)
        try:
            attr.write(data, mtype=mem_type)
        finally:
            attr.close()


#: h5py's variable-length UTF-8 string (what it stores a ``str`` as).
_STR = h5py.string_dtype()
#: Shapes and types whose creation properties / HDF5 types are kept (cleared when full).
_KEPT_TYPES = 256
_CHECKED_DCPL: dict = {}
_TYPES: dict = {}


def file_type(dtype: np.dtype):
    """The HDF5 type h5py stores ``dtype`` as (records included): to compare with a
    dataset's, ``ds.id.get_type().equal(file_type(dtype))``, without building it again."""
    return _types(dtype)[0]


def _types(dtype: np.dtype) -> tuple:
    """The HDF5 file type (logical) and memory type (bit for bit) of ``dtype``, as h5py's
    attribute and dataset writers build them, kept per dtype (a record's fields are part
    of it; a string's encoding is not, so it is added)."""
    from h5py import h5t
    key = (dtype, h5py.check_string_dtype(dtype) if dtype.kind == "O" else None)
    t = _TYPES.get(key)
    if t is None:
        if len(_TYPES) >= _KEPT_TYPES:
            _TYPES.clear()
        t = _TYPES[key] = (h5t.py_create(dtype, logical=True), h5t.py_create(dtype))
    return t


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
