"""Building FMUs from C sources: a ``.fmu`` compiled with the system C compiler and cached
by a hash of the model description, the sources and the build recipe."""
from __future__ import annotations

import hashlib
import os
import subprocess
import tempfile
import xml.etree.ElementTree as ET
import zipfile
from pathlib import Path

from ..errors import SimulationError
from .common import _one_line

# Part of the hash: changing how the binary is built must invalidate the cache.
_BUILD_RECIPE = b"twinmon-build/1: cc -O2 -shared -fPIC <sources/*.c> -lm"
_ZIP_DATE = (2020, 1, 1, 0, 0, 0)   # fixed, so that the same build gives the same bytes
_FMU_MODE = 0o644                   # a built .fmu is a shareable file, not a private one


def _source_files(src_dir: Path) -> list[Path]:
    sources = src_dir / "sources"
    files = [src_dir / "modelDescription.xml"]
    if sources.is_dir():
        # is_file() and read_bytes() follow symbolic links: a source shared with another
        # FMU folder through a link is hashed and packed by its content.
        files += sorted(p for p in sources.rglob("*") if p.is_file())
    return files


def source_hash(src_dir: Path) -> str:
    """SHA-256 over ``modelDescription.xml`` and every file under ``sources/``.

    Parameters
    ----------
    src_dir : Path
        FMU source folder.

    Returns
    -------
    str
        Hex digest; covers each file's relative path and content (sorted; symbolic links
        are followed) and the build recipe.
    """
    src_dir = Path(src_dir)
    h = hashlib.sha256(_BUILD_RECIPE)
    for f in _source_files(src_dir):
        h.update(f.relative_to(src_dir).as_posix().encode() + b"\0")
        h.update(f.read_bytes())
        h.update(b"\0")
    return h.hexdigest()


def _model_head(md_path: Path) -> tuple[str, str]:
    """``(fmiVersion, modelIdentifier)`` of a source folder's model description."""
    try:
        root = ET.parse(md_path).getroot()
    except (OSError, ET.ParseError) as e:
        raise SimulationError(f"cannot read {md_path}: {_one_line(e)}") from None
    version = root.get("fmiVersion", "")
    if not (version == "2.0" or version.startswith("3.")):
        raise SimulationError(f"{md_path}: fmiVersion {version!r} is not supported "
                              "(FMI 2.0 or 3.0)")
    for kind in ("CoSimulation", "ModelExchange"):
        el = root.find(kind)
        if el is not None and el.get("modelIdentifier"):
            return version, el.get("modelIdentifier")
    raise SimulationError(f"{md_path} declares no modelIdentifier")


def _fmi_headers() -> Path:
    import fmpy
    return Path(os.path.dirname(fmpy.__file__)) / "c-code"


def _binary_dir(fmi_version: str) -> str:
    """Folder of the shared library inside the FMU: FMI 3 names platforms by a tuple."""
    import fmpy
    return f"binaries/{fmpy.platform_tuple if fmi_version.startswith('3') else fmpy.platform}"


def build_fmu(src_dir: Path | str, force: bool = False) -> Path:
    """Compile an FMU source folder (FMI 2.0 or 3.0) into a ``.fmu`` (cached by :func:`source_hash`).

    Parameters
    ----------
    src_dir : Path or str
        Folder with ``modelDescription.xml`` and ``sources/``.  The FMI version is read from
        the model description: FMI 2.0 binaries go to ``binaries/linux64/``, FMI 3.0 ones to
        ``binaries/x86_64-linux/`` (fmpy's platform names).
    force : bool
        Rebuild even when the cached ``.fmu`` exists.

    Returns
    -------
    Path
        ``<src_dir>/.build/<hash[:16]>/<modelIdentifier>.fmu``, mode 0644.

    Raises
    ------
    SimulationError
        The sources are missing or do not compile (names the folder and the first error line).
    """
    import fmpy

    src_dir = Path(src_dir).resolve()
    md = src_dir / "modelDescription.xml"
    if not md.is_file():
        raise SimulationError(f"{src_dir} has no modelDescription.xml")
    fmi_version, identifier = _model_head(md)
    c_files = sorted((src_dir / "sources").glob("*.c"))
    if not c_files:
        raise SimulationError(f"{src_dir / 'sources'} holds no C sources")
    digest = source_hash(src_dir)
    out_dir = src_dir / ".build" / digest[:16]
    out = out_dir / f"{identifier}.fmu"
    if out.is_file() and not force:
        if out.stat().st_mode & 0o777 != _FMU_MODE:
            try:    # cached by an older twinmon that left it private (0600)
                os.chmod(out, _FMU_MODE)
            except OSError:
                pass
        return out

    out_dir.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory(prefix="twinmon-build-") as tmp:
        lib_rel = f"{_binary_dir(fmi_version)}/{identifier}{fmpy.sharedLibraryExtension}"
        lib = Path(tmp) / lib_rel
        lib.parent.mkdir(parents=True)
        cmd = ["cc", "-O2", "-shared", "-fPIC", "-I", str(_fmi_headers()),
               "-I", str(src_dir / "sources"), *map(str, c_files), "-o", str(lib), "-lm"]
        try:
            proc = subprocess.run(cmd, capture_output=True, text=True)
        except OSError as e:
            raise SimulationError(f"cannot compile FMU sources in {src_dir}: {e}") from None
        if proc.returncode != 0:
            lines = [ln for ln in proc.stderr.splitlines() if ln.strip()]
            first = next((ln for ln in lines if "error" in ln.lower()),
                         lines[0] if lines else f"cc exited with code {proc.returncode}")
            raise SimulationError(f"cannot compile FMU sources in {src_dir}: {first.strip()}")

        entries = [("modelDescription.xml", md), (lib_rel, lib)]
        entries += [(p.relative_to(src_dir).as_posix(), p)
                    for p in _source_files(src_dir)[1:]]
        fd, tmp_fmu = tempfile.mkstemp(suffix=".fmu.tmp", dir=out_dir)
        try:
            with os.fdopen(fd, "wb") as fh, zipfile.ZipFile(fh, "w", zipfile.ZIP_DEFLATED) as zf:
                for name, path in entries:
                    info = zipfile.ZipInfo(name, date_time=_ZIP_DATE)
                    info.compress_type = zipfile.ZIP_DEFLATED
                    info.external_attr = 0o644 << 16
                    zf.writestr(info, path.read_bytes())
            os.chmod(tmp_fmu, _FMU_MODE)      # mkstemp creates 0600
            os.replace(tmp_fmu, out)
        except BaseException:
            if os.path.exists(tmp_fmu):
                os.unlink(tmp_fmu)
            raise
    return out


def resolve_fmu(path) -> Path:
    """The ``.fmu`` to run for ``path``: a source folder is built (cached), a ``.fmu`` is used as is.

    Raises
    ------
    SimulationError
        ``path`` is neither an FMU source folder nor a ``.fmu`` file.
    """
    p = Path(path)
    if p.is_dir() and (p / "modelDescription.xml").is_file() and (p / "sources").is_dir():
        return build_fmu(p)
    if p.is_file() and p.suffix.lower() == ".fmu":
        return p
    raise SimulationError(f"{p} is neither a .fmu file nor an FMU source folder "
                          "(modelDescription.xml + sources/)")

