"""The ``reduce`` section: the Karhunen-Loeve reduction and the Gaussian-process surrogate
built on it."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Literal, Optional


@dataclass(frozen=True)
class ReduceConfig:
    #: Keep the fewest Karhunen-Loeve modes whose variance ratio reaches this.
    variance_threshold: float = 0.99999
    #: "log": reduce log(output), so the error is relative at every time step (the early,
    #: small samples of a start-up are otherwise learnt to absolute, not relative, accuracy);
    #: only for an output that stays > 0. "auto": log when every training value is > 0.
    transform: Literal["auto", "log", "none"] = "auto"
    max_modes: int = 8
    kernel: Literal["squared_exponential", "matern52", "matern32", "exponential"] = "matern52"
    trend: Literal["constant", "linear", "quadratic"] = "linear"
    #: Further channels (keys of ``model.channels``) that get a surrogate of their own, built
    #: like the output's but with transform ``auto``; None: every channel the design
    #: recorded; []: the output only (each channel costs about one more reduce).
    channels: Optional[tuple[str, ...]] = None

    def _check(self):
        if not 0 < self.variance_threshold <= 1:
            yield "variance_threshold", "must lie in (0, 1]", self.variance_threshold
        if self.max_modes < 1:
            yield "max_modes", "must be >= 1", self.max_modes
