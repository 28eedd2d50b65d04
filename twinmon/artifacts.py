"""HDF5 artifacts: atomic writes, provenance, schema checks.

Every stage writes one HDF5 file through :func:`write_artifact`: the content goes to a
temporary file in the target's folder and is renamed over the final name only once complete,
so a crash or a bad input never leaves a half-written or clobbered artifact. Root attributes
record what made the file (schema, version, time, config, input hashes, seed). Readers go
through :func:`open_artifact`, which checks the schema and names the file, the expected and the
found schema on a mismatch.
"""
from __future__ import annotations

import contextlib
import datetime as _dt
import hashlib
import json
import os
from collections import OrderedDict
from collections.abc import Mapping
from pathlib import Path
from typing import Any, Callable, Iterator, Sequence

import h5py
import numpy as np

from .errors import ArtifactError, OutputBusyError, ReadError, TwinmonError, UsageError

#: Lowest HDF5 file-format version of the fleet-sized artifacts (``write_artifact(compact=True)``):
#: HDF5 >= 1.10 indexes a one-chunk dataset without a B-tree (about 2.3 kB less per dataset,
#: a quarter of a unit's posterior) and is read by every h5py of the last years.
COMPACT_LIBVER = ("v110", "v110")

#: Current major version of each artifact kind. Bump on an incompatible layout change.
SCHEMAS = {
    "simulations": 1,
    "surrogate": 1,
    "observations": 1,
    "truth": 1,
    "posterior": 2,
    "forecast": 1,
    "gap": 2,
    "backtest": 1,
}


#: Earlier major versions a reader still accepts (the reader handles their layout).
#: posterior/1, gap/1: one dataset per field and unit (the /2 layouts pack a unit's per-year
#: results into one compound dataset).
READABLE = {"posterior": (1,), "gap": (1,)}


def schema_name(kind: str) -> str:
    return f"twinmon.{kind}/{SCHEMAS[kind]}"


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
    from . import __version__
    return __version__


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


# ---------------------------------------------------------------------------------------
# Output locks: one writer per output
# ---------------------------------------------------------------------------------------
_held: dict[str, list] = {}


def _forget_locks_in_child() -> None:
    """In a forked child (a pool worker): close the inherited lock descriptors, so that the
    lock dies with the process that took it, not with the last of its children. Only closed,
    never unlocked: ``flock`` belongs to the open file, and unlocking here would release the
    parent's lock."""
    for fd, _ in _held.values():
        try:
            os.close(fd)
        except OSError:
            pass
    _held.clear()


if hasattr(os, "register_at_fork"):
    os.register_at_fork(after_in_child=_forget_locks_in_child)


def lock_path(path: str | os.PathLike) -> Path:
    path = Path(path)
    return path.with_name(f".{path.name}.lock")


@contextlib.contextmanager
def output_lock(path: str | os.PathLike, command: str = "twinmon") -> Iterator[None]:
    """Hold an advisory lock on ``path`` (a file or a folder) while writing it.

    The lock is ``flock`` on a hidden ``.<name>.lock`` file beside ``path`` holding the
    holder's PID and command: the kernel drops it when the holder dies (even by ``kill -9``).
    Forked children do not keep it (their copy of the descriptor is closed at fork), and a
    lock whose recorded holder is dead (kept by some other process that inherited it) is
    taken over with a warning on stderr. Re-entrant within one process.

    Raises
    ------
    OutputBusyError
        Another process holds the lock; the message names it. Nothing was touched.
    """
    import fcntl
    import sys
    path = Path(path)
    key = str(path.resolve())
    if key in _held:
        _held[key][1] += 1
        try:
            yield
        finally:
            _held[key][1] -= 1
        return
    lp = lock_path(path)
    lp.parent.mkdir(parents=True, exist_ok=True)
    while True:
        fd = os.open(lp, os.O_RDWR | os.O_CREAT | os.O_CLOEXEC, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 4096, 0).decode("utf-8", "replace").strip() or "another process"
            pid = _holder_pid(holder)
            if pid is not None and not _alive(pid) and _unlink_if_same(lp, fd):
                os.close(fd)
                sys.stderr.write(f"twinmon: warning: {path}: the lock of {holder} was left by a "
                                 "process that is gone; taking it over\n")
                continue
            os.close(fd)
            raise OutputBusyError(f"{path} is being written by {holder}; wait for it to finish "
                                  "or choose another output") from None
        # The previous holder unlinks the lock file on release: if we locked a file that is
        # no longer the one under that name, start again with the current one.
        try:
            same = os.stat(lp).st_ino == os.fstat(fd).st_ino
        except FileNotFoundError:
            same = False
        if same:
            break
        os.close(fd)
    argv = " ".join(Path(sys.argv[0]).name if i == 0 else a for i, a in enumerate(sys.argv[:2]))
    try:
        os.pwrite(fd, f"{argv or command} (pid {os.getpid()})".encode(), 0)
    except OSError as exc:
        # A full disk: the writer cannot write its output either; leave no empty lock file.
        try:
            os.unlink(lp)
        except OSError:
            pass
        os.close(fd)
        raise OSError(exc.errno, f"cannot write: {exc.strerror}", str(path)) from None
    _held[key] = [fd, 1]
    try:
        yield
    finally:
        del _held[key]
        try:
            os.unlink(lp)          # while still locked, so no one else holds this inode
        except OSError:
            pass
        os.close(fd)


def _holder_pid(holder: str) -> int | None:
    """The PID in a lock file's ``<command> (pid N)`` text, or None."""
    import re
    m = re.search(r"\(pid (\d+)\)\s*$", holder)
    return int(m.group(1)) if m else None


def _unlink_if_same(lp: Path, fd: int) -> bool:
    """Remove the lock file ``lp`` if it is still the one open as ``fd`` (a new holder may
    have replaced it meanwhile: that one is not stale)."""
    try:
        if os.stat(lp).st_ino != os.fstat(fd).st_ino:
            return True             # already replaced: try again with the current one
        os.unlink(lp)
        return True
    except FileNotFoundError:
        return True
    except OSError:
        return False


def locks_output(arg: str, command: str) -> Callable:
    """Decorate a stage function so that it holds the output lock of its argument ``arg``
    for the whole call: from before it reads what it will overwrite or continue (an
    ``--update`` plans from the output's present content) to the rename of the new file.
    Locking only at the write let two writers plan from the same old file and the last one
    replace the other's work. The lock is re-entrant: :func:`write_artifact` inside takes it
    again at no cost."""
    import functools
    import inspect

    def wrap(func):
        sig = inspect.signature(func)

        @functools.wraps(func)
        def locked(*args, **kwargs):
            bound = sig.bind(*args, **kwargs)
            bound.apply_defaults()
            target = bound.arguments[arg]
            if target is None:                  # nothing written
                return func(*args, **kwargs)
            parent = Path(target).parent
            made = not parent.exists()
            parent.mkdir(parents=True, exist_ok=True)
            try:
                with output_lock(target, command):
                    return func(*args, **kwargs)
            except BaseException:
                if made:                        # a failed stage leaves no empty folder
                    try:
                        parent.rmdir()
                    except OSError:
                        pass
                raise
        return locked
    return wrap


def remove_stale_temporaries(path: str | os.PathLike) -> list[Path]:
    """Remove ``.<name>.<pid>.tmp`` files beside ``path`` whose writer is gone (a crash or
    ``kill -9`` before it could clean up). Call with the output lock held."""
    path = Path(path)
    removed = []
    for tmp in path.parent.glob(f".{path.name}.*.tmp"):
        pid = tmp.name[len(path.name) + 2:-4]
        if pid.isdigit() and not _alive(int(pid)):
            try:
                if tmp.is_dir():
                    import shutil
                    shutil.rmtree(tmp)
                else:
                    tmp.unlink()
                removed.append(tmp)
            except OSError:
                pass
    return removed


def _alive(pid: int) -> bool:
    if pid == os.getpid():
        return True
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


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


def open_artifact(path: str | os.PathLike, kind: str) -> h5py.File:
    """Open an artifact read-only after checking it exists and has the expected schema.

    Raises
    ------
    ArtifactError
        Missing file, not HDF5, or a schema other than ``twinmon.<kind>/<major>``.
    """
    path = Path(path)
    if not path.exists():
        raise ArtifactError(f"{path}: file not found (expected a {kind} artifact)")
    if path.is_dir():
        raise ArtifactError(f"{path}: is a folder (expected a {kind} artifact file)")
    if not os.access(path, os.R_OK):
        raise ReadError(f"{path}: permission denied (cannot read the {kind} artifact)")
    try:
        f = _ArtifactFile(path, "r")
    except OSError:
        raise ArtifactError(f"{path}: not a readable HDF5 file (expected a {kind} artifact)") from None
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


def get(group: h5py.Group, name: str, path: str | os.PathLike | None = None) -> np.ndarray:
    """Read a dataset, raising :class:`ArtifactError` naming the file and the dataset when
    it is missing (an artifact of the right schema but the wrong content)."""
    if name not in group:
        where = path or group.file.filename
        raise ArtifactError(f"{where}: dataset {group.name.rstrip('/')}/{name} is missing")
    ds = group[name]
    if h5py.check_string_dtype(ds.dtype) is not None:
        return np.array([s.decode() if isinstance(s, bytes) else s for s in ds[()]])
    return ds[()]


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

    def each(self) -> Iterator[tuple[str, Any]]:
        """Every unit in the file's order, read in one opening of the file (a stage that
        needs them all: opening the file per unit costs more than reading a small one).
        The cache is not filled."""
        self._check_unchanged()
        with open_artifact(self.path, self.kind) as f:
            for unit in self._names:
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


def is_up_to_date(output: str | os.PathLike, kind: str, config: str,
                  inputs: Sequence[str | os.PathLike]) -> bool:
    """True when ``output`` exists, has the right schema, was made from the same config
    section and from inputs with the same hashes. Used by ``twinmon run`` to skip stages."""
    output = Path(output)
    if not output.exists():
        return False
    if not _readable_hdf5(output):
        return False                    # damaged: the stage makes it again
    prov = read_provenance(output)
    if prov.get("schema") != schema_name(kind) or prov.get("config") != config:
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

