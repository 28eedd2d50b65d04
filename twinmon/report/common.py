"""What every figure and page of the report shares: colours, the figure saver, the config's words.

Nothing in the report names a machine: the output's label and units, the health indicator's
name, label, units and limit all come from the config (:class:`Words`).
"""
from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Any, Optional

import numpy as np

from ..config import Config
from ..safety import Indicator

#: Resolution of every PNG (dots per inch).
DPI = 150
#: Colours of the units, in order of first appearance (tab10 without red: red means "limit").
UNIT_COLOURS = ["#1f77b4", "#ff7f0e", "#2ca02c", "#9467bd", "#8c564b", "#e377c2",
                "#7f7f7f", "#bcbd22", "#17becf"]
LIMIT_COLOUR = "#d62728"

SECTIONS = ("observations", "surrogate", "calibration", "forecast", "backtest", "diagnose")
SECTION_TITLES = {
    "observations": "Observations",
    "surrogate": "Reduced model (surrogate) against the FMU",
    "calibration": "Calibration: degradation inputs per year",
    "forecast": "Forecast: trends, failure probability, time to failure",
    "backtest": "Back-test: how good past forecasts were on this history",
    "diagnose": "Sim-to-real gap (diagnose)",
}
SKIP_HINTS = {
    "observations": "no observations file given (--observations)",
    "surrogate": "no surrogate artifact given (run `twinmon reduce`)",
    "calibration": "no posterior artifact given (run `twinmon calibrate`)",
    "forecast": "no forecast artifact given (run `twinmon forecast`)",
    "backtest": "no back-test artifact given (run `twinmon backtest`)",
    "diagnose": "no gap artifact given (run `twinmon diagnose`)",
}


def withheld_words(reason: str = "", forced: bool = False) -> str:
    """Why a prognosis is withheld (or was forced), at a glance: its estimates sit on the
    design box's edge (the twin may fit the data well), else the twin misses the plant."""
    from ..forecast.judge import box_bound_of
    why = ("the estimates sit on the twin's box" if box_bound_of(reason)
           else "the twin misses the plant")
    return f"FORCED prognosis: {why}" if forced else f"prognosis withheld: {why}"


# ---------------------------------------------------------------------------------------
# The config's words
# ---------------------------------------------------------------------------------------
def qty(value: float, units: str) -> str:
    """``30 s``; a dimensionless value (units ``1`` or empty) without units."""
    return f"{value:g}" if units in ("", "1") else f"{value:g} {units}"


def axis_label(label: str, units: str) -> str:
    """``<label> (<units>)`` axis label; ``(-)`` for a dimensionless quantity."""
    return f"{label} ({'-' if units in ('', '1') else units})"


@dataclass(frozen=True)
class Words:
    """The config's names for what the report shows.

    Attributes
    ----------
    out_label, out_units : str
        The observed output's words and units (``model.output``).
    out_axis : str
        Axis label of the output, e.g. ``"<label> (<units>)"``.
    ind : Indicator
        The health indicator (name, label, units, limit, sense, rule, fmt).
    ind_axis : str
        Axis label of the indicator, e.g. ``"<name> (<units>)"``.
    var_label, var_units : str
        Words and units of the variable the indicator is computed from.
    on_output : bool
        The indicator is computed from the observed output (its level can be drawn there).
    has_nonphysical : bool
        The model flags a non-physical twin (which counts as unsafe).
    """

    out_label: str
    out_units: str
    out_axis: str
    ind: Indicator
    ind_axis: str
    var_label: str
    var_units: str
    on_output: bool
    has_nonphysical: bool

    @classmethod
    def from_config(cls, cfg: Config) -> "Words":
        out = cfg.model.output
        ind = Indicator.from_config(cfg)
        on_output = ind.variable == out.variable
        vlabel, vunits = cfg.model.variable_words(ind.variable)
        return cls(out.label, out.units, axis_label(out.label, out.units), ind,
                   axis_label(ind.name, ind.units), vlabel, vunits, on_output,
                   bool(cfg.model.nonphysical))

    @property
    def kind(self) -> str:
        return self.ind.spec.kind

    @property
    def side(self) -> str:
        """``above`` or ``below``: where the indicator is unsafe."""
        return "above" if self.ind.sense > 0 else "below"

    @property
    def limit_text(self) -> str:
        """The limit with its units, e.g. ``30 s``."""
        return qty(self.ind.limit, self.ind.units)

    @property
    def unsafe_text(self) -> str:
        """``<label> (<name>) above <limit>``, plus the non-physical mode when the model has one."""
        text = f"its {self.ind.label} ({self.ind.name}) is {self.side} {self.limit_text}"
        return text + (" or its twin leaves the physical domain" if self.has_nonphysical else "")


def named(uf) -> list:
    """The components a forecast's verdict names (its attribution's), or []."""
    att = getattr(uf, "attribution", None)
    return list(getattr(att, "named", None) or ()) if att is not None else []


def state_words(root_cause: Optional[str], reason: str = "", components=()) -> str:
    """``healthy``, ``<component> fault``, ``<a> and <b> faults`` (root cause ``both``, its
    ``components``; ``several faults`` without them), or ``prognosis withheld`` and why: the
    twin misses the plant, or (``reason``, the forecast's status reason, says so) the
    estimates sit on the design box's edge."""
    if root_cause is None:
        return "unknown"
    if root_cause == "withheld":
        return withheld_words(reason)
    if root_cause == "healthy":
        return "healthy"
    if root_cause == "both":
        return " and ".join(components) + " faults" if components else "several faults"
    if root_cause == "ambiguous":
        return "degrading, component ambiguous"
    return f"{root_cause} fault"


# ---------------------------------------------------------------------------------------
# Small formatting functions
# ---------------------------------------------------------------------------------------
def pct(p: Optional[float]) -> str:
    if p is None or not np.isfinite(p):
        return "n/a"
    if 0 < p < 0.005:
        return "<1 %"
    return f"{100 * p:.0f} %"


def plain(obj: Any) -> Any:
    """JSON-able copy (numpy scalars and arrays made plain, non-finite floats -> None)."""
    if isinstance(obj, dict):
        return {str(k): plain(v) for k, v in obj.items()}
    if isinstance(obj, (list, tuple)):
        return [plain(v) for v in obj]
    if isinstance(obj, np.ndarray):
        return plain(obj.tolist())
    if isinstance(obj, np.generic):
        return plain(obj.item())
    if isinstance(obj, float) and not np.isfinite(obj):
        return None
    if isinstance(obj, Path):
        return str(obj)
    return obj


def input_label(cfg: Config, name: str) -> str:
    spec = cfg.model.inputs.get(name)
    return axis_label(name, spec.units if spec is not None else "")


def indicator_rows(ind: Indicator, time: np.ndarray, values: np.ndarray) -> np.ndarray:
    """The health indicator per row of ``values`` [n, n_t] (missing samples, NaN, left out
    row by row); shape [n]."""
    return np.asarray(ind(np.asarray(time, float), np.atleast_2d(np.asarray(values, float))),
                      float)


# ---------------------------------------------------------------------------------------
# Figures
# ---------------------------------------------------------------------------------------
class Figures:
    """Saves figures as PNG files and remembers them for the HTML.

    ``suffix`` and ``units`` name a group of units drawn apart (a large fleet's units are
    drawn a few at a time): ``fig7_trends_2.png``, titled "... (A, B, C)".

    With a ``pool`` (of worker processes forked with this process's matplotlib settings), a
    figure is pickled and laid out, drawn and written there while the next one is built
    here: the layout and the rasterising are most of a figure's cost (0.3-1.9 s against
    0.01-0.04 s to pickle it). A figure that does not pickle is written here. The PNGs are
    the same pixel for pixel; :meth:`finish` waits for them."""

    def __init__(self, folder: Path, pool=None):
        self.folder = folder
        self.items: list[dict] = []
        self.suffix = ""
        self.units: list[str] = []
        self._pool = pool
        self._pending: list = []

    def new(self, width: float, height: float, **kw):
        from matplotlib.backends.backend_agg import FigureCanvasAgg
        from matplotlib.figure import Figure
        # At the PNG's resolution: the layout is computed at the figure's (write_png).
        fig = Figure(figsize=(width, height), layout="constrained", dpi=DPI, **kw)
        FigureCanvasAgg(fig)
        return fig

    def save(self, fig, name: str, section: str, title: str, caption: str) -> None:
        name += self.suffix
        wrap_suptitle(fig)
        if self.units:
            title += f" ({', '.join(self.units)})"
        path = self.folder / f"{name}.png"
        blob = None
        if self._pool is not None:
            import pickle
            try:
                blob = pickle.dumps(fig, protocol=pickle.HIGHEST_PROTOCOL)
            except (pickle.PicklingError, AttributeError, TypeError):
                blob = None          # an artist holding a local function, say
        if blob is None:
            write_png(fig, path)
        else:
            self._pending.append(self._pool.submit(_save_pickled, blob, str(path)))
        self.items.append({"name": name, "section": section, "title": title,
                           "caption": caption, "file": f"figures/{name}.png", "_path": path})

    def finish(self) -> None:
        """Wait for the figures the pool is writing; raise the first one's error."""
        pending, self._pending = self._pending, []
        for future in pending:
            future.result()


#: Characters of a figure title per inch of figure width (matplotlib's "large" title font,
#: 12 pt, averages about 6.5 pt a character): beyond, the title is cut at the edges.
TITLE_CHARS_PER_INCH = 10.5


def wrap_suptitle(fig) -> None:
    """Wrap the figure's title to its width, line by line (a one-input figure is narrow and
    its title, written for several panels, would be clipped on both sides)."""
    import textwrap
    title = getattr(fig, "_suptitle", None)
    if title is None or not title.get_text():
        return
    width = max(int(fig.get_figwidth() * TITLE_CHARS_PER_INCH), 20)
    lines = [ln for line in title.get_text().split("\n")
             for ln in (textwrap.wrap(line, width) or [""])]
    title.set_text("\n".join(lines))


def freeze_inherited() -> None:
    """Pool initializer: set the objects a forked worker inherits outside the collector.

    :func:`_relink_transforms` then walks only what the worker made itself (the figures it
    unpickles). On a 300-unit report (25 figures, 2 workers), walking the whole inherited
    heap for each figure took it from 20.5-20.6 s to 23.0-23.8 s; with the freeze it takes
    21.1-21.5 s (20.6-21.5 s without any re-keying). The garbage collector no longer touches
    those pages either, so fewer of the parent's pages get copied into the worker."""
    import gc
    gc.freeze()


def write_png(fig, path) -> None:
    """Write ``fig`` as a PNG of :data:`DPI` dots per inch, laid out once.

    ``savefig`` on a figure with a layout engine draws it twice: once with drawing disabled
    only to run the layout, then for the pixels. Run here first and the engine removed, the
    layout is the same and the figure is drawn once: the same pixels.
    """
    import matplotlib
    engine = fig.get_layout_engine()
    if engine is not None and fig.dpi == DPI:
        engine.execute(fig)
        # None removes the engine, unless the user's matplotlibrc asks for one by default.
        with matplotlib.rc_context({"figure.autolayout": False,
                                    "figure.constrained_layout.use": False}):
            fig.set_layout_engine(None)
    fig.savefig(path, dpi=DPI)


def _save_pickled(blob: bytes, path: str) -> None:
    """Pool task: write a pickled figure as :meth:`Figures.save` would."""
    write_png(load_pickled_figure(blob), path)


def load_pickled_figure(blob: bytes):
    """A figure pickled by :meth:`Figures.save`, ready to draw in this process."""
    import pickle
    fig = pickle.loads(blob)
    _relink_transforms()
    return fig


def _relink_transforms() -> None:
    """Key every matplotlib transform's parents by their ids in this process.

    A transform tells its parents that it changed through a dict keyed by ``id(parent)``,
    whose weak references pop their key when a parent dies. Unpickling keeps the keys of the
    process that pickled the figure. In a worker forked from that process, the transforms
    made while drawing often land at those very addresses: a new one overwrites a stale key,
    and its death pops it, so an unpickled parent is no longer told of a change and draws with
    a stale matrix -- a line cut short, a box missing. Measured before this fix, on a small
    three-unit report drawn with two workers: such collisions in 20 of 100 figures (in each of
    10 reports), and a figure visibly wrong in 1 report of 10 to 3 of 5 depending on the load
    (CI failed on it). After it: no stale key and no collision in 60 figures, none wrong. It walks
    every object the collector tracks: in the figure pool only those the worker made itself
    (:func:`freeze_inherited`), ~60 ms for the whole heap of a process with the report's
    modules loaded, against 0.3-1.9 s to draw a figure.
    """
    import gc
    import weakref

    from matplotlib.transforms import TransformNode
    for node in gc.get_objects():
        # type(), not isinstance(): a dead weak proxy raises on its __class__.
        links = getattr(node, "_parents", None) if issubclass(type(node), TransformNode) \
            else None
        if not links:
            continue
        parents = [ref() for ref in links.values()]
        fresh: dict = {}
        for parent in parents:
            if parent is not None:
                key = id(parent)
                fresh[key] = weakref.ref(parent, lambda _, pop=fresh.pop, k=key: pop(k, None))
        node._parents = fresh


def indicator_limit_line(ax, words: Words) -> None:
    """The indicator's limit on an indicator axis (horizontal, red, dashed)."""
    ax.axhline(words.ind.limit, color=LIMIT_COLOUR, ls="--", lw=1.2,
               label=f"{words.limit_text} limit ({words.side} is unsafe)")
