"""Digest of every array in the HDF5 artifacts under a folder, to show a change is bit-identical.

``python benchmarks/tools/digest.py DIR [DIR ...] > before.txt``, change the code, run the same
commands again, then ``diff before.txt after.txt``. Each line is ``file:dataset sha256`` of the
dataset's raw bytes, dtype and shape; attributes are left out, because ``created``, input
hashes of rewritten files and the version change on every run, while the arrays must not.
"""
from __future__ import annotations

import hashlib
import sys
from pathlib import Path

import h5py
import numpy as np


def digest(folder: Path) -> list[str]:
    """One ``path:dataset sha256`` line per dataset of every ``*.h5`` below ``folder``."""
    lines = []
    for path in sorted(folder.rglob("*.h5")):
        with h5py.File(path, "r") as f:
            def visit(name, obj):
                if isinstance(obj, h5py.Dataset):
                    arr = np.asarray(obj[()])
                    h = hashlib.sha256()
                    h.update(str((arr.dtype.str, arr.shape)).encode())
                    h.update(arr.tobytes() if arr.dtype.kind != "O" else repr(arr.tolist()).encode())
                    lines.append(f"{path.relative_to(folder)}:{name} {h.hexdigest()[:16]}")
            f.visititems(visit)
    return lines


if __name__ == "__main__":
    for arg in sys.argv[1:]:
        for line in digest(Path(arg)):
            print(f"{arg}/{line}")
