"""Which way each input degrades the unit: from the config, else inferred through the twin.

The slope tests (:mod:`.trend`), detection and attribution test an input's slope on its
degrading side. ``model.inputs.<name>.degrading`` gives it; without it
:func:`degrading_directions` probes the twin around the nominal point and keeps the sign
only when the indicator's change clearly exceeds the surrogate's own error; otherwise the
input is tested two-sided, with a warning that says so.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from ..config import Config
from .twin import SOURCE_SURROGATE, evaluate_twin


@dataclass
class Direction:
    """Which way an input degrades the unit, and how that was decided.

    ``sign`` +1 (raising the input moves the indicator towards unsafe), -1, or 0 (unknown);
    ``source`` ``config`` or ``inferred``; ``effect`` the indicator change over the probe
    (indicator units) and ``noise`` the surrogate's own indicator error (same units)."""

    sign: int
    source: str
    effect: float = float("nan")
    noise: float = float("nan")
    note: str = ""


#: An inferred direction must exceed the surrogate's own indicator error this many times.
DIRECTION_MARGIN = 3.0
#: Half-width of the probe around the nominal point, as a fraction of each input's range.
DIRECTION_STEP = 0.25


def degrading_directions(cfg: Config, surrogate) -> dict[str, Direction]:
    """Degrading direction of every input: from the config, else inferred from the twin.

    Inference: the indicator at the nominal point +- 25 % of the input's range (clipped to
    the box), through the twin (:func:`~.twin.evaluate_twin`: the surrogate, or the FMU for an
    indicator on another variable). The sign of the change that moves the indicator towards
    unsafe is kept only when the change exceeds ``DIRECTION_MARGIN`` times the surrogate's
    own indicator error on held-out FMU runs (:func:`indicator_noise`; 0 for the FMU).
    Otherwise the direction is 0 and the input is tested two-sided, with a note that says so.
    """
    from ..safety import Indicator
    ind = Indicator.from_config(cfg)
    x0 = np.array([s.nominal for s in cfg.model.inputs.values()])
    rng = cfg.model.bounds[:, 1] - cfg.model.bounds[:, 0]
    out, probe = {}, {}
    for i, (name, spec) in enumerate(cfg.model.inputs.items()):
        if spec.degrading is not None:
            out[name] = Direction(1 if spec.degrading == "up" else -1, "config")
            continue
        step = np.zeros_like(x0)
        step[i] = DIRECTION_STEP * rng[i]
        probe[name] = (np.maximum(x0 - step, cfg.model.bounds[:, 0]),
                       np.minimum(x0 + step, cfg.model.bounds[:, 1]))
    if not probe:
        return out
    twin = evaluate_twin(cfg, surrogate, np.array([p for pair in probe.values() for p in pair]))
    noise = (indicator_noise(cfg, surrogate, surrogate.X_test, surrogate.Y_test)
             if np.any(twin.source == SOURCE_SURROGATE) else 0.0)
    for k, name in enumerate(probe):
        v_dn, v_up = twin.value[2 * k], twin.value[2 * k + 1]
        if not (np.isfinite(v_dn) and np.isfinite(v_up)):
            # A level never reached (inf) at one end: the direction is plain, the size not.
            same = (v_dn == v_up) or np.isnan(v_dn) or np.isnan(v_up)
            d = 0 if same else (1 if (v_up > v_dn) == (ind.sense > 0) else -1)
            out[name] = Direction(d, "inferred", float(v_up - v_dn) if not same else 0.0, noise,
                                  note="" if d else f"{name}: the twin gives no usable "
                                  f"{ind.name} at the probe; degrading direction unknown, "
                                  f"tested two-sided; set model.inputs.{name}.degrading")
            continue
        delta = float(v_up - v_dn)
        if delta != 0 and abs(delta) > DIRECTION_MARGIN * noise:
            out[name] = Direction(int(np.sign(delta)) * ind.sense, "inferred", delta, noise)
        else:
            out[name] = Direction(0, "inferred", delta, noise, note=(
                f"{name}: its effect on {ind.name} over the probe ({delta:+.3g} {ind.units}) "
                f"is not above {DIRECTION_MARGIN:g}x the surrogate's own error "
                f"({noise:.3g} {ind.units}): degrading direction unknown, tested two-sided; "
                f"set model.inputs.{name}.degrading to up or down"))
    return out


def indicator_noise(cfg: Config, surrogate, X_test: np.ndarray, Y_test: np.ndarray) -> float:
    """RMS error of the health indicator computed from the surrogate vs the FMU's test runs
    (indicator units); 0 when there is no usable test run."""
    from ..safety import Indicator
    if len(X_test) == 0 or np.size(Y_test) == 0:
        return 0.0
    ind = Indicator.from_config(cfg)
    a = ind(surrogate.time, surrogate.predict(X_test))
    b = ind(surrogate.time, Y_test)
    ok = np.isfinite(a) & np.isfinite(b)
    return float(np.sqrt(np.mean((a[ok] - b[ok]) ** 2))) if ok.any() else 0.0
