"""The ``simulate`` section: the design of training and test runs of the FMU and where
they run."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal


@dataclass(frozen=True)
class SimulateConfig:
    train_size: int = 128
    test_size: int = 64
    design: Literal["lhs", "sobol", "halton"] = "lhs"
    #: Worker processes; 0 means one per core.
    workers: int = 0
    #: ``dask``: on a Dask cluster (the ``dask`` section; docs/cluster.md). Also used by
    #: ``forecast``'s FMU runs.
    executor: Literal["process", "serial", "dask"] = "process"
    #: Runs flushed to the partial artifact at a time (what a crash can lose).
    chunk_size: int = 64

    def _check(self):
        if self.train_size < 2:
            yield "train_size", "must be >= 2", self.train_size
        if self.test_size < 0:
            yield "test_size", "must be >= 0", self.test_size
        if self.workers < 0:
            yield "workers", "must be >= 0", self.workers
        if self.chunk_size < 1:
            yield "chunk_size", "must be >= 1", self.chunk_size
