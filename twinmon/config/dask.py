"""The ``dask`` section: the Dask cluster that runs the stages whose ``executor`` is
``dask`` (never changes a result)."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional


@dataclass(frozen=True)
class DaskConfig:
    """Where the stages whose ``executor`` is ``dask`` run (docs/cluster.md).

    ``address`` null: a ``LocalCluster`` on this machine, as many worker processes as the
    stage's ``workers`` (0: one per core), one thread each; ``tcp://host:8786``: the running
    scheduler there (its workers must run one thread each). ``timeout``: seconds allowed to
    reach the scheduler or start the local workers before the command fails."""

    address: Optional[str] = None
    timeout: float = 10.0

    def _check(self):
        if self.address is not None and (not self.address.strip()
                                         or any(c.isspace() for c in self.address)):
            yield "address", "expected a scheduler address such as tcp://host:8786, or " \
                "null for a local cluster", self.address
        if self.timeout <= 0:
            yield "timeout", "must be > 0 (seconds)", self.timeout
