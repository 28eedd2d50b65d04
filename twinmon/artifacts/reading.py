"""Reading artifacts: the schema-checked opening, datasets by name, units read on demand,
and the full read that finds damage before an artifact is continued."""
from __future__ import annotations

import json
import os
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import h5py
import numpy as np

from ..errors import ArtifactError, ReadError, TwinmonError
from .schema import READABLE, schema_name


def _a(word: str) -> str:
    """``word`` with its article: "an observations", "a forecast"."""
    return ("an " if word[:1].lower() in "aeiou" else "a ") + word


def open_artifact(path: str | os.PathLike, kind: str) -> h5py.File:
    """Open an artifact read-only after checking it exists and has the expected schema.

    Raises
    ------
    ArtifactError
        Missing file, not HDF5, or a schema other than ``twinmon.<kind>/<major>``.
    """
    path = Path(path)
    if not path.exists():
        raise ArtifactError(f"{path}: file not found (expected {_a(kind)} artifact)")
    if path.is_dir():
        raise ArtifactError(f"{path}: is a folder (expected {_a(kind)} artifact file)")
    if not os.access(path, os.R_OK):
        raise ReadError(f"{path}: permission denied (cannot read the {kind} artifact)")
    try:
        f = _ArtifactFile(path, "r")
    except OSError:
        raise ArtifactError(f"{path}: not a readable HDF5 file (expected {_a(kind)} artifact)") from None
    f.twinmon_path = path
    found = f.attrs.get("schema", None)
    if isinstance(found, bytes):
        found = found.decode()
    expected = schema_name(kind)
    if found != expected and found not in {f"twinmon.{kind}/{v}" for v in READABLE.get(kind, ())}:
        f.close()
        raise ArtifactError(f"{path}: schema is {found!r}, expected {expected!r}")
    return f


class _ArtifactFile(h5py.File):
    """An artifact open for reading: damage found while reading it (a corrupt object header,
    a missing attribute, a truncated dataset) leaves the ``with`` block as one
    :class:`ArtifactError` naming the file, not as an h5py traceback."""

    twinmon_path: Path = Path("<artifact>")

    def __exit__(self, typ, exc, tb):
        super().__exit__(typ, exc, tb)
        if exc is not None and isinstance(exc, (KeyError, OSError, RuntimeError, ValueError,
                                                TypeError, json.JSONDecodeError)) \
                and not isinstance(exc, TwinmonError):
            what = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
            raise ArtifactError(f"{self.twinmon_path}: damaged or incomplete artifact ({what}); "
                                "re-run the stage that made it") from None
        return False


def get(group: h5py.Group, name: str, path: str | os.PathLike | None = None) -> np.ndarray:
    """Read a dataset, raising :class:`ArtifactError` naming the file and the dataset when
    it is missing (an artifact of the right schema but the wrong content).

    Numbers and records go through the low-level API (:func:`read_dataset`): the same
    array as ``group[name][()]`` at a third of its cost, which a fleet's stages pay once
    per dataset of every unit (reading a unit's posterior for the forecast: 15 ms of
    which 9 were h5py's look-ups and dtype conversions). Strings come back as ``str``."""
    try:
        dsid = h5py.h5d.open(group.id, name.encode())
    except KeyError:
        where = path or group.file.filename
        raise ArtifactError(f"{where}: dataset {group.name.rstrip('/')}/{name} is missing") \
            from None
    out = read_dataset(dsid)
    if out is None:          # strings, or a dataspace with no shape: h5py's own reading
        ds = h5py.Dataset(dsid)
        if h5py.check_string_dtype(ds.dtype) is not None:
            return np.array([s.decode() if isinstance(s, bytes) else s for s in ds[()]])
        return ds[()]
    return out


def read_dataset(dsid: "h5py.h5d.DatasetID") -> np.ndarray | None:
    """A numeric or record dataset read whole through the low-level API, its numpy dtype
    built once per file type (h5py's high-level read builds it again on every call); a
    scalar dataset as a numpy scalar, as ``ds[()]`` gives it. None for what this does not
    read (strings, variable-length data, a null dataspace)."""
    from h5py import h5s, h5t
    shape = dsid.shape
    if shape is None:
        return None
    tid = dsid.get_type()
    for known, dtype in _READ_TYPES:
        if tid.equal(known):
            break
    else:
        if tid.get_class() in (h5t.STRING, h5t.VLEN, h5t.REFERENCE, h5t.OPAQUE):
            return None
        dtype = dsid.dtype
        if dtype.hasobject:  # variable-length members
            return None
        _READ_TYPES.insert(0, (tid, dtype))
        del _READ_TYPES[_READ_TYPES_KEPT:]
    out = np.empty(shape, dtype)
    if out.size:
        dsid.read(h5s.ALL, h5s.ALL, out)
    return out[()] if out.ndim == 0 else out


#: File types met lately and their numpy dtypes (:func:`read_dataset`), newest first.
_READ_TYPES: list = []
_READ_TYPES_KEPT = 16


def get_shape(group: h5py.Group, name: str, path: str | os.PathLike | None = None) -> tuple:
    """The shape of a dataset, without reading it (missing: as :func:`get`)."""
    if name not in group:
        where = path or group.file.filename
        raise ArtifactError(f"{where}: dataset {group.name.rstrip('/')}/{name} is missing")
    return group[name].shape


class LazyUnits(Mapping):
    """The units of an artifact, each read when it is looked up.

    A read-only mapping unit name -> whatever ``read(f, unit, path)`` returns from the open
    artifact, in the file's order. ``in``, ``len`` and iterating the names read no unit, so a
    fleet's artifact never sits in memory whole; the ``cache`` units read last are kept (a
    stage often looks a unit up twice in a row). Each look-up opens the file through
    :func:`open_artifact` (damage reads as :class:`ArtifactError`); a file replaced or
    removed since the names were listed is refused rather than mixed with the first one.
    """

    def __init__(self, path: str | os.PathLike, kind: str, names: Sequence[str],
                 read: Callable[[h5py.File, str, Path], Any], cache: int = 4):
        self.path = Path(path)
        self.kind = kind
        self._names = list(names)
        self._known = set(self._names)
        self._read = read
        self._cache: OrderedDict[str, Any] = OrderedDict()
        self._size = cache
        self._stamp = _stamp(self.path)

    def __getitem__(self, unit: str) -> Any:
        if unit not in self._known:
            raise KeyError(unit)
        if unit in self._cache:
            self._cache.move_to_end(unit)
            return self._cache[unit]
        self._check_unchanged(f" (reading unit {unit})")
        with open_artifact(self.path, self.kind) as f:
            value = self._read(f, unit, self.path)
        self._cache[unit] = value
        while len(self._cache) > self._size:
            self._cache.popitem(last=False)
        return value

    def each(self, names: Sequence[str] | None = None) -> Iterator[tuple[str, Any]]:
        """Every unit in the file's order (or those of ``names``, in their order), read in
        one opening of the file (a stage that needs them all: opening the file per unit
        costs more than reading a small one). The cache is not filled.

        Raises
        ------
        KeyError
            A unit of ``names`` is not in the file.
        """
        missing = [u for u in names or () if u not in self._known]
        if missing:
            raise KeyError(missing[0])
        self._check_unchanged()
        with open_artifact(self.path, self.kind) as f:
            for unit in self._names if names is None else names:
                yield unit, self._read(f, unit, self.path)

    def _check_unchanged(self, reading: str = "") -> None:
        """The file must be the one whose units were listed (not replaced or removed)."""
        try:
            same = _stamp(self.path) == self._stamp
        except OSError:
            same = False
        if not same:
            raise ArtifactError(f"{self.path}: replaced or removed since it was opened"
                                f"{reading}; run the command again")

    def __contains__(self, unit: object) -> bool:
        return unit in self._known

    def __iter__(self) -> Iterator[str]:
        return iter(self._names)

    def __len__(self) -> int:
        return len(self._names)

    def __repr__(self) -> str:
        return f"LazyUnits({str(self.path)!r}, {len(self)} units)"


def _stamp(path: Path) -> tuple:
    st = os.stat(path)
    return st.st_ino, st.st_size, st.st_mtime_ns


def verify_artifact(path: str | os.PathLike, kind: str) -> None:
    """Read every dataset of an artifact, so that damage anywhere (a flipped byte caught by
    a chunk's checksum, a truncated file) is found before the artifact is continued.

    ``--update`` copies the earlier output and adds to it: without this, bytes of it that
    the update does not read would be carried into the new file unchecked.

    Raises
    ------
    ArtifactError
        Naming the file and the first damaged dataset.
    """
    def read(name, obj):
        if isinstance(obj, h5py.Dataset):
            try:
                obj[()]
            except (OSError, ValueError, RuntimeError, TypeError) as exc:
                what = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
                raise ArtifactError(f"{path}: damaged artifact, dataset /{name} cannot be read "
                                    f"({what}); re-run the stage that made it without "
                                    "--update") from None
        return None
    with open_artifact(path, kind) as f:
        f.visititems(read)
