"""Several recorded channels in one likelihood.

When a plant records more than the output (a motor speed, a pressure, a current: the
config's ``model.channels``), each recorded channel that ``reduce`` learnt a surrogate of
enters the likelihood with its own noise:

    log p(x | y)  =  log prior(x)  -  1/2 sum_c sum_t (y_ct - f_ct(x))^2 / (sigma_c^2 + s_ct^2)

The channels are stacked: :class:`StackedSurrogate` predicts the channels' transients side by
side, ``[n, n_ch * n_t]`` (the output first, then the channels in the order chosen), and the
observation row and the variance row are concatenated the same way. The log-density, the MAP,
the samplers and the goodness of fit therefore work on the stacked record unchanged. With the
output alone, calibrate uses the output's surrogate itself (the stack is never built), so
output-only results are those of a single-channel run, bit for bit.

Noise per channel: the observations file's ``noise_std[channel]``; else, for the output only,
``calibrate.noise_std``; else estimated from the unit's own records through the channel's
surrogate (:func:`~twinmon.calibrate.density.estimate_noise`).
"""
from __future__ import annotations

import os
from typing import Optional

import numpy as np

from ..config import Config
from ..errors import ArtifactError, InputDataError
from .density import estimate_noise_checked


class StackedSurrogate:
    """Surrogates of several channels on one time grid, seen as one surrogate.

    Parameters
    ----------
    parts : dict of str to Surrogate
        Channel name -> its surrogate, the output first; every part has the same inputs, box
        and time grid (they come from one ``surrogate.h5``).

    Attributes
    ----------
    names : list of str
        Channel names in stacking order.
    input_names : list of str
    bounds : ndarray, shape [d, 2]
    n_t : int
        Samples per channel.
    time : ndarray, shape [n_ch * n_t], s
        Time of each stacked sample (the grid once per channel): a window by time holds
        every channel's samples in it.
    blocks : list of (str, slice)
        Each channel's columns in a stacked row.
    """

    def __init__(self, parts: dict):
        self.parts = dict(parts)
        self.names = list(self.parts)
        first = self.parts[self.names[0]]
        self.input_names, self.bounds = first.input_names, first.bounds
        self.n_t = first.time.size
        for name, s in self.parts.items():
            if s.time.shape != first.time.shape or not np.allclose(s.time, first.time):
                raise ArtifactError(f"the surrogate of channel {name!r} has another time grid "
                                    "than the output's; re-run reduce")
        self.time = np.tile(first.time, len(self.names))
        self.blocks = [(n, slice(i * self.n_t, (i + 1) * self.n_t))
                       for i, n in enumerate(self.names)]

    @property
    def output(self):
        """The output's surrogate (the first part)."""
        return self.parts[self.names[0]]

    def scale(self, X: np.ndarray) -> np.ndarray:
        return self.output.scale(X)

    def in_box(self, X: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        return self.output.in_box(X, tol)

    def fingerprint(self) -> str:
        """The output surrogate's fingerprint (what ``forecast`` predicts through)."""
        return self.output.fingerprint()

    def predict(self, X: np.ndarray) -> np.ndarray:
        """Stacked transients, shape [n, n_ch * n_t], each channel in its units."""
        return np.concatenate([s.predict(X) for s in self.parts.values()], axis=1)

    def predict_with_var(self, X: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Stacked prediction and predictive variance, both shape [n, n_ch * n_t]."""
        out = [s.predict_with_var(X) for s in self.parts.values()]
        return (np.concatenate([o[0] for o in out], axis=1),
                np.concatenate([o[1] for o in out], axis=1))

    def predict_var(self, X: np.ndarray) -> np.ndarray:
        return self.predict_with_var(X)[1]

    def stack(self, rows: dict) -> np.ndarray:
        """Per-channel arrays [..., n_t] (name -> array) side by side, [..., n_ch * n_t]."""
        return np.concatenate([np.asarray(rows[n], float) for n in self.names], axis=-1)

    def noise_var(self, std: np.ndarray) -> np.ndarray:
        """Noise variance per stacked sample, shape [n_ch * n_t], from one standard deviation
        per channel ``std`` [n_ch] (channel units)."""
        return np.repeat(np.asarray(std, float) ** 2, self.n_t)


def select_channels(cfg: Config, surrogate, obs, surrogate_path) -> tuple[list[str], list[str]]:
    """The further channels that enter the likelihood, and warnings about the others.

    ``calibrate.channels`` when set: each must have a surrogate and be recorded for every
    unit. Otherwise every channel that every unit's observations carry and the surrogate
    models; a recorded channel left out is named in a warning.

    Parameters
    ----------
    surrogate : Surrogate
        The output's surrogate (its ``channel_names`` lists the channels the file models).
    obs : Observations

    Raises
    ------
    ArtifactError
        ``calibrate.channels`` names a channel the surrogate file does not model.
    InputDataError
        ``calibrate.channels`` names a channel a unit's observations lack.
    """
    modelled = list(getattr(surrogate, "channel_names", []))
    output = cfg.model.output.name
    recorded = {unit: [c for c in u.channels if c != output] for unit, u in obs.units.items()}
    wanted = cfg.calibrate.channels
    if wanted is not None:
        for ch in wanted:
            if ch not in modelled:
                raise ArtifactError(f"{surrogate_path}: no surrogate of channel {ch!r} "
                                    f"(calibrate.channels; the file models "
                                    f"{', '.join(modelled) or 'none'}); re-run simulate and "
                                    "reduce with it in model.channels")
            for unit, have in recorded.items():
                if ch not in have:
                    raise InputDataError(f"{obs.path}: /units/{unit}/{ch} is missing "
                                         "(calibrate.channels names it)")
        return list(wanted), []
    everywhere = [c for c in modelled if all(c in have for have in recorded.values())]
    seen = list(dict.fromkeys(c for have in recorded.values() for c in have))
    warnings = []
    unmodelled = [c for c in seen if c not in modelled]
    if unmodelled:
        where = "model.channels" if cfg.reduce.channels is None else \
            "model.channels and reduce.channels"
        warnings.append(f"the observations carry channel(s) {', '.join(unmodelled)} that "
                        f"{surrogate_path} does not model: left out of the likelihood (to use "
                        f"them: list them in {where}, re-run simulate and reduce)")
    partial = [c for c in seen if c in modelled and c not in everywhere]
    if partial:
        warnings.append(f"channel(s) {', '.join(partial)} are not recorded for every unit: "
                        "left out of the likelihood (set calibrate.channels to use them)")
    return everywhere, warnings


def load_surrogate(path: str | os.PathLike, output: str, channels: list[str]):
    """The surrogate the likelihood predicts through: the output's alone without further
    channels, else a :class:`StackedSurrogate` of the output and ``channels``."""
    from ..reduce import read_channel_surrogates, read_surrogate
    surrogate = read_surrogate(path)
    if not channels:
        return surrogate
    return StackedSurrogate({output: surrogate, **read_channel_surrogates(path, channels)})


def channel_noise(cfg: Config, unit_obs, stack: StackedSurrogate, output_noise: float,
                  output_source: str, unit: str = "",
                  warnings: Optional[list] = None) -> tuple[np.ndarray, dict]:
    """Noise standard deviation of each stacked channel for one unit.

    Parameters
    ----------
    unit_obs : UnitObservations
    stack : StackedSurrogate
    output_noise : float
        The output's noise (output units), already resolved (file, config or estimated).
    output_source : str
        Where it came from.
    unit : str
        The unit's name, for the warnings.
    warnings : list, optional
        Gets a line for each channel whose estimated noise level had to be taken from the
        residuals' second differences (:meth:`~.density.NoiseEstimate.warning`).

    Returns
    -------
    std : ndarray, shape [n_ch]
        Channel units, in stacking order.
    info : dict
        Channel -> ``{"std": float, "source": "file" | "config" | "estimated" |
        "differences"}`` (:attr:`~.density.NoiseEstimate.source`).
    """
    std, info = [output_noise], {stack.names[0]: {"std": float(output_noise),
                                                  "source": output_source}}
    for ch in stack.names[1:]:
        if ch in unit_obs.noise_std:
            s, src = float(unit_obs.noise_std[ch]), "file"
        else:
            est = estimate_noise_checked(stack.parts[ch], cfg, unit_obs.channels[ch])
            s, src = est.std, est.source
            if est.structured and warnings is not None:
                warnings.append(est.warning(unit, ch,
                                            cfg.model.channels[ch].units))
        std.append(s)
        info[ch] = {"std": s, "source": src}
    return np.array(std), info


def stacked_rows(unit_obs, stack: Optional[StackedSurrogate], output: str) -> np.ndarray:
    """A unit's records [n_y, n_t] (output only) or [n_y, n_ch * n_t] (stacked)."""
    if stack is None:
        return unit_obs.channels[output]
    return stack.stack({n: unit_obs.channels[n] for n in stack.names})
