"""Stage ``report``: figures, a self-contained HTML report, ``summary.json`` and a terminal summary.

Every section is optional: it is rendered when its artifact is given and skipped with a note
when it is not, so a report can be made after any prefix of the pipeline (observations only,
then the surrogate, the posterior, the forecast, the sim-to-real gap).

Nothing here names a machine: the output's label and units, the health indicator's name,
label, units and limit and the inputs' components all come from the config
(:class:`~twinmon.report.common.Words`).

Figures (one PNG each, 150 dpi; numbers follow the paper's), by module:

===========================  ======================  =============================================
figure                       module                  shows
===========================  ======================  =============================================
``fig2_last_transients``     ``fig_observations``    last recorded transient of every unit, where
                                                     the indicator is read, its level or limit
``fig3_indicator_history``   ``fig_observations``    observed health indicator per year, limit
``fig5_surrogate``           ``fig_surrogate``       surrogate against the FMU on held-out test
                                                     runs, error as % of the output's range
``fig6_estimates``           ``fig_calibration``     posterior estimates per year, 90 % intervals
``fig7_trends``              ``fig_forecast``        linear trends with 90 % prediction intervals
``fig8_marginals``           ``fig_forecast``        forecast input distributions, selected years
``fig9_indicator_forecast``  ``fig_forecast``        indicator distribution per year, P(unsafe),
                                                     failure year
``diag_residual_map``        ``fig_diagnose``        residuals (observation - twin) by year/time
``diag_candidates``          ``fig_diagnose``        candidate unmodelled effects by BIC gain
``diag_overlay``             ``fig_diagnose``        one affected year: observation, base twin,
                                                     augmented twin
``fleet_failure``            ``fig_fleet``           a large fleet's time to failure: units by
                                                     years to failure, failures per year ahead
===========================  ======================  =============================================

Other modules: ``load`` (reading the artifacts, all before anything is drawn), ``summary``
(per-unit words, ``summary.json``, the terminal text), ``html`` (the page, its CSS and
tables), ``common`` (colours, the figure saver, the config's words), ``fleet`` (a large fleet's
ranking, units at risk and the units drawn in detail), ``stage`` (:func:`report`).

A fleet of more than ``report.detail_units`` units opens on a fleet overview and draws per-unit
figures for the units at risk and those asked for only, a few units per figure.

Everything is written to a temporary folder beside ``output_dir`` and moved into place at the
end, ``index.html`` last, so a failing report never leaves a half-written ``index.html``.

Plotting lives in this package and only here (matplotlib, Agg canvas, no pyplot global state).
"""
from __future__ import annotations

from .common import (DPI, LIMIT_COLOUR, SECTIONS, UNIT_COLOURS, Figures, Words,
                     indicator_rows)
from .fig_calibration import fig_estimates
from .fig_diagnose import fig_candidates, fig_overlay, fig_residual_map
from .fig_forecast import fig_indicator_forecast, fig_marginals, fig_trends
from .fig_observations import fig_indicator_history, fig_last_transients
from .fig_surrogate import fig_surrogate
from .stage import is_up_to_date, made_from, report
from .summary import ReportSummary
from .unit_summary import UnitSummary

__all__ = ["report", "is_up_to_date", "made_from", "ReportSummary", "UnitSummary", "Words",
           "indicator_rows", "DPI", "SECTIONS", "UNIT_COLOURS", "LIMIT_COLOUR", "Figures",
           "fig_last_transients", "fig_indicator_history", "fig_surrogate", "fig_estimates",
           "fig_trends", "fig_marginals", "fig_indicator_forecast", "fig_residual_map",
           "fig_candidates", "fig_overlay"]
