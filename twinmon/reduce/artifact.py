"""The ``surrogate.h5`` artifact: writing a surrogate (the output's at the root, each further
channel's under ``/channels/<name>``) and rebuilding it from the stored arrays."""
from __future__ import annotations

import json
import os
from pathlib import Path

import numpy as np

from .. import artifacts
from ..config import Config
from ..errors import ArtifactError
from .surrogate import Surrogate, Validation


#: Config sections recorded in the artifact (and compared by ``twinmon run``).
SECTIONS = ("model", "reduce")


def write_surrogate(path, s: Surrogate, val: Validation, cfg: Config, inputs,
                    channels: dict | None = None) -> None:
    """Write ``surrogate.h5``: the output's surrogate at the root, each further channel's
    (``channels``: name -> (Surrogate, Validation)) under ``/channels/<name>``."""
    with artifacts.write_artifact(path, "surrogate", config=cfg.section_yaml(*SECTIONS),
                                  inputs=inputs) as f:
        _put_surrogate(f, s, val)
        f.attrs["channels"] = json.dumps(list(channels or {}))
        for ch, (cs, cv) in (channels or {}).items():
            _put_surrogate(f.create_group(f"channels/{ch}"), cs, cv)


def _put_surrogate(f, s: Surrogate, val: Validation) -> None:
    """One surrogate's attributes and arrays into a group (the file's root or a channel's)."""
    f.attrs["input_names"] = json.dumps(s.input_names)
    f.attrs["kernel"] = s.kernel
    f.attrs["trend"] = s.trend
    f.attrs["transform"] = s.transform
    f.attrs["output_units"] = s.units
    f.attrs["validation"] = artifacts.json_attr(val.as_dict())
    f.attrs["content_id"] = s.fingerprint()
    put = artifacts.put
    put(f, "time", s.time, "s", "sample times")
    put(f, "bounds", s.bounds, "input units", "training box, rows (low, high) per input")
    zu = f"log({s.units})" if s.transform == "log" else s.units
    put(f, "mean", s.mean, zu, "mean training transient (after the transform)")
    put(f, "basis", s.basis, zu, "lifting of mode coefficients: z = mean + xi @ basis")
    put(f, "eigenvalues", s.eigenvalues, f"({zu})^2", "Karhunen-Loeve eigenvalues")
    put(f, "truncation_var", s.truncation_var, f"({zu})^2",
        "training variance not captured by the kept modes, per time step")
    put(f, "X_train", s.X_train, "1", "training inputs scaled to the unit box")
    put(f, "xi_train", s.xi_train, "1", "mode coefficients of the training transients")
    put(f, "scales", s.scales, "1 (unit box)", "kernel scale per mode and input")
    put(f, "amplitudes", s.amplitudes, "1", "kernel amplitude per mode")
    put(f, "X_test", s.X_test, "input units", "held-out test inputs, one row per FMU run")
    put(f, "Y_test", s.Y_test, s.units, "held-out FMU transients of the test inputs")
    g = f.create_group("trend_coefficients")
    for k, c in enumerate(s.trend_coefs):
        put(g, str(k), c, "1", f"trend coefficients of mode {k}")


def read_surrogate(path: str | os.PathLike) -> Surrogate:
    """Rebuild the output's surrogate from ``surrogate.h5`` (schema checked); its
    ``channel_names`` lists the further channels the file holds."""
    path = Path(path)
    with artifacts.open_artifact(path, "surrogate") as f:
        s = _get_surrogate(f, path)
        s.channel_names = json.loads(f.attrs.get("channels", "[]"))
        return s


def read_channel_surrogates(path: str | os.PathLike,
                            names: list[str] | None = None) -> dict[str, Surrogate]:
    """The further channels' surrogates of ``surrogate.h5``: ``names`` (default: all).

    Raises
    ------
    ArtifactError
        A named channel has no surrogate in the file (written before channels were
        reduced, or left out by ``reduce.channels``).
    """
    path = Path(path)
    with artifacts.open_artifact(path, "surrogate") as f:
        have = json.loads(f.attrs.get("channels", "[]"))
        out = {}
        for ch in (have if names is None else names):
            if ch not in have or f"channels/{ch}" not in f:
                raise ArtifactError(f"{path}: no surrogate of channel {ch!r} (the file has "
                                    f"{', '.join(have) or 'none'}); re-run simulate and reduce "
                                    "with the channel in model.channels (and reduce.channels)")
            out[ch] = _get_surrogate(f[f"channels/{ch}"], path)
        return out


def _get_surrogate(f, path: Path) -> Surrogate:
    """A surrogate from the group :func:`_put_surrogate` wrote."""
    get = lambda name: artifacts.get(f, name, path)  # noqa: E731
    K = get("basis").shape[0]
    coefs = [artifacts.get(f["trend_coefficients"], str(k), path) for k in range(K)]
    return Surrogate(input_names=json.loads(f.attrs["input_names"]), bounds=get("bounds"),
                     time=get("time"), mean=get("mean"), basis=get("basis"),
                     eigenvalues=get("eigenvalues"), truncation_var=get("truncation_var"),
                     X_train=get("X_train"), xi_train=get("xi_train"),
                     kernel=str(f.attrs["kernel"]), trend=str(f.attrs["trend"]),
                     scales=get("scales"), amplitudes=get("amplitudes"),
                     trend_coefs=coefs, transform=str(f.attrs["transform"]),
                     units=str(f.attrs["output_units"]),
                     X_test=get("X_test") if "X_test" in f else np.empty((0, 0)),
                     Y_test=get("Y_test") if "Y_test" in f else np.empty((0, 0)),
                     content_id=str(f.attrs.get("content_id", "")))


def read_validation(path: str | os.PathLike) -> dict:
    """The output surrogate's validation on the test runs (:meth:`Validation.as_dict`)."""
    with artifacts.open_artifact(path, "surrogate") as f:
        return json.loads(f.attrs["validation"])


def read_channel_validation(path: str | os.PathLike) -> dict[str, dict]:
    """Each further channel's validation on the test runs, by channel ({} when none)."""
    with artifacts.open_artifact(path, "surrogate") as f:
        return {ch: json.loads(f[f"channels/{ch}"].attrs["validation"])
                for ch in json.loads(f.attrs.get("channels", "[]"))}
