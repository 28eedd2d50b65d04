"""Temporary files left beside an output by a writer that is gone."""
from __future__ import annotations

import os
from pathlib import Path

from .locks import _alive


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
