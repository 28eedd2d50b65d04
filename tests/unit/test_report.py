"""report: figures, a self-contained HTML page, summary.json, on a small real pipeline.

The pipeline is built once per module in a tmp folder: a small design through the real FMU,
the surrogate, three fabricated units over four years, and the later stages (calibrate,
forecast, diagnose) when their modules are present, with small sample sizes.
"""
from __future__ import annotations

import base64
import hashlib
import importlib.util
import json
import re
from pathlib import Path

import numpy as np
import pytest

from twinmon.artifacts import file_sha256
from twinmon.config import load_config
from twinmon.errors import ArtifactError
from twinmon.report import indicator_rows, report
from twinmon.safety import Indicator

from ..conftest import CONFIGS, write_yaml

PNG_MAGIC = b"\x89PNG\r\n\x1a\n"


def _has(module: str) -> bool:
    return importlib.util.find_spec(f"twinmon.{module}") is not None


@pytest.fixture(scope="module")
def pipeline(tmp_path_factory, fmu_path):
    """Artifacts of a small pipeline; keys are report() argument names (None: not built)."""
    tmp = tmp_path_factory.mktemp("report")
    cfg_path = write_yaml(tmp / "c.yaml", {
        "extends": str(CONFIGS / "fleet.yaml"),
        "simulate": {"train_size": 40, "test_size": 8, "executor": "serial"},
        "calibrate": {"chains": 2, "samples": 300, "burn_in": 150, "workers": 1, "ess_warn": 100.0, "max_extensions": 1},
        "forecast": {"samples": 300, "horizon": 5},
        "diagnose": {"candidates": ["valve.opening_time", "sensor.tau"], "workers": 1},
        "fabricate": {"years": 4, "units": {
            "Park": {"trajectories": {"motor_damping": {"start": 9.5, "slope": 0.05},
                                      "pump_coef": {"start": 3.75, "slope": -0.02}}},
            "Colt": {"trajectories": {"motor_damping": {"start": 10.5, "slope": 0.05},
                                      "pump_coef": {"start": 3.2, "slope": -0.25}}},
            # A valve that opens slowly from year 3: a gap diagnose can find.
            "Monk": {"trajectories": {"motor_damping": {"start": 12.0, "slope": 3.0},
                                      "pump_coef": {"start": 3.65, "slope": -0.02}},
                     "effects": {"valve.opening_time": {"value": 8.0, "onset": 3}}},
        }},
    })
    cfg = load_config(cfg_path)
    from twinmon.fabricate import fabricate
    from twinmon.reduce import reduce
    from twinmon.simulate import simulate
    art = {"observations": tmp / "fleet.h5", "truth": tmp / "truth.h5",
           "simulations": tmp / "simulations.h5", "surrogate": tmp / "surrogate.h5",
           "posterior": None, "forecast": None, "gap": None}
    simulate(cfg, art["simulations"])
    reduce(cfg, art["simulations"], art["surrogate"])
    fabricate(cfg, art["observations"], art["truth"])
    if _has("calibrate"):
        from twinmon.calibrate import calibrate
        art["posterior"] = tmp / "posterior.h5"
        calibrate(cfg, art["surrogate"], art["observations"], art["posterior"])
        if _has("forecast"):
            from twinmon.forecast import forecast
            art["forecast"] = tmp / "forecast.h5"
            forecast(cfg, art["posterior"], art["surrogate"], art["forecast"])
    if _has("diagnose"):
        from twinmon.diagnose import diagnose
        art["gap"] = tmp / "gap.h5"
        diagnose(cfg, art["observations"], art["gap"], workers=1)
    return cfg, cfg_path, tmp, art


@pytest.fixture(scope="module")
def full(pipeline):
    """The whole report, its figures drawn by a pool of two worker processes."""
    _, cfg_path, tmp, art = pipeline
    out = tmp / "report_full"
    return report(load_config(cfg_path, ["report.workers=2"]), out, **art), out


def _sha(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def _embedded_pngs(text: str) -> list[bytes]:
    return [base64.b64decode(m) for m in
            re.findall(r'src="data:image/png;base64,([A-Za-z0-9+/=]+)"', text)]


def test_full_report_is_self_contained_with_a_figure_per_section(pipeline, full):
    cfg, _, tmp, art = pipeline
    summary, out = full
    text = (out / "index.html").read_text()
    assert text.startswith("<!DOCTYPE html>") and text.rstrip().endswith("</html>")
    assert 'src="http' not in text and "<link" not in text and "<script" not in text
    pngs = _embedded_pngs(text)
    assert len(pngs) == len(summary.figures) and all(p.startswith(PNG_MAGIC) for p in pngs)
    # The embedded images are the PNG files written beside the page (compared by digest: a
    # failing comparison of raw PNG bytes has pytest diff megabytes for over ten minutes).
    files = {f["name"]: file_sha256(out / f["file"]) for f in summary.figures}
    assert sorted(_sha(p) for p in pngs) == sorted(files.values())
    for unit in ("Park", "Colt", "Monk"):
        assert unit in text
    names = set(files)
    assert {"fig2_last_transients", "fig3_indicator_history", "fig5_surrogate"} <= names
    expected_sections = {"observations", "surrogate"}
    if art["posterior"]:
        assert "fig6_estimates" in names
        expected_sections.add("calibration")
    if art["forecast"]:
        assert {"fig7_trends", "fig8_marginals", "fig9_indicator_forecast"} <= names
        expected_sections.add("forecast")
    if art["gap"]:
        assert {"diag_residual_map", "diag_candidates"} <= names
        expected_sections.add("diagnose")
    assert {s for s, v in summary.sections.items() if v == "rendered"} == expected_sections
    assert not list(tmp.glob(".report_full*"))                 # no temporary folder left


def test_summary_json_is_derived_from_the_artifacts(pipeline, full):
    cfg, _, _, art = pipeline
    summary, out = full
    data = json.loads((out / "summary.json").read_text())
    assert data == json.loads(json.dumps(summary.as_dict()))
    keys = {"health", "root_cause", "failure_year", "p_unsafe", "action", "plan",
            "estimates", "confidence", "diagnose", "last_indicator"}
    assert set(data["units"]) == {"Park", "Colt", "Monk"}
    for unit in data["units"].values():
        assert keys <= set(unit)
    assert data["surrogate"]["n_test"] == 8
    assert data["surrogate"]["max_range_error"] >= data["surrogate"]["mean_range_error"] > 0
    # The pump's flow stays away from 0: the relative error is defined too.
    assert data["surrogate"]["max_rel_error"] >= data["surrogate"]["mean_rel_error"] > 0
    assert data["indicator"]["name"] == Indicator.from_config(cfg).name
    assert data["output"]["units"] == cfg.model.output.units
    if art["posterior"]:
        from twinmon.calibrate import read_posterior
        post = read_posterior(art["posterior"])
        for u, p in post.units.items():
            est = data["units"][u]["estimates"]["pump_coef"]
            assert est["year"] == int(p.years[-1])
            assert est["mean"] == pytest.approx(float(p.mean[-1, 1]))
            assert est["q05"] <= est["mean"] <= est["q95"]
        assert set(data["calibration"]["units"]) == set(post.units)
    if art["forecast"]:
        from twinmon.forecast import read_forecast
        fc = read_forecast(art["forecast"])
        for u, f in fc.units.items():
            s = data["units"][u]
            assert s["root_cause"] == f.root_cause and s["failure_year"] == f.failure_year
            if f.root_cause == "healthy" and f.status == "ok":
                # How large a fault the healthy verdict rules out.
                assert "a fault shows in this record half the time from" in s["confidence"]
            assert s["plan"] == f.plan
            if f.failure_year is not None:
                k = int(np.flatnonzero(f.years_future == f.failure_year)[0])
                assert s["p_unsafe"] == pytest.approx(float(f.p_unsafe[k]))
                assert f"year {f.failure_year - 1}" in s["action"] or "now" in s["action"]
    if art["gap"]:
        from twinmon.diagnose import read_gap
        gap = read_gap(art["gap"])
        for u, g in gap.units.items():
            assert data["units"][u]["diagnose"]["verdict"] == g.verdict


def test_the_diagnose_lines_say_how_the_noise_was_known_and_where_the_gap_lies(pipeline,
                                                                               tmp_path):
    """A gap.h5 whose noise was estimated and whose gap no single window holds: each unit's
    diagnose line says how well the noise is known, the gap is spread over the record (it
    read "the whole record window"), and summary.json has diagnose's noise."""
    import dataclasses

    from twinmon.diagnose import read_gap, write_gap
    from twinmon.fmu import resolve_fmu
    cfg, _, tmp, art = pipeline
    if not (art["gap"] and art["forecast"]):
        pytest.skip("needs the diagnose and forecast stages")
    gap = read_gap(art["gap"])
    units = {u: dataclasses.replace(g, noise_dof=20.0, where_windows=[])
             for u, g in gap.units.items()}
    write_gap(tmp_path / "gap.h5", units, cfg, gap.time,
              [art["observations"], resolve_fmu(cfg.model.fmu)])
    report(cfg, tmp_path / "rep", **{**art, "gap": tmp_path / "gap.h5"})
    data = json.loads((tmp_path / "rep" / "summary.json").read_text())
    for u, g in units.items():
        s = data["units"][u]
        assert "diagnose (noise estimated from the record to +-16 %)" in s["confidence"]
        assert s["diagnose"]["noise_dof"] == 20.0
        if g.verdict == "effect":
            assert "the gap is spread over the record (no window is significant alone)" \
                in s["confidence"] and "whole record" not in s["confidence"]
            if s["status"] == "ok":
                assert f"diagnose finds {g.effects[0]}" in s["action"]
                assert "though each year's fit passes calibrate's test" in s["action"]


def test_terminal_summary_has_one_line_per_unit(pipeline, full):
    _, _, _, art = pipeline
    summary, _ = full
    lines = summary.terminal().splitlines()
    for unit, s in summary.units.items():
        line = next(x for x in lines if x.startswith(unit))
        if s.failure_year is not None:
            assert f"fails in year {s.failure_year}" in line
            # The point forecast beside the year to act by, where they differ.
            med = s.median_failure_year
            assert (f"median year {med}" in line) == (med is not None
                                                       and med != s.failure_year)
        assert s.action in line


def test_report_with_observations_only_skips_the_other_sections(pipeline):
    cfg, _, tmp, art = pipeline
    out = tmp / "report_obs"
    s = report(cfg, out, observations=art["observations"])
    assert [f["name"] for f in s.figures] == ["fig2_last_transients", "fig3_indicator_history"]
    assert s.sections["observations"] == "rendered"
    text = (out / "index.html").read_text()
    for sec in ("surrogate", "calibration", "forecast", "diagnose"):
        assert s.sections[sec].startswith("skipped")
        assert f'<h2 id="{sec}">' in text
    assert text.count("Section skipped") == 5    # all but observations
    assert all(u.health == "unknown" and u.last_indicator > 0 for u in s.units.values())
    assert len(_embedded_pngs(text)) == 2
    assert json.loads((out / "summary.json").read_text())["units"].keys() == s.units.keys()


def test_wrong_schema_artifact_names_the_file_and_writes_nothing(pipeline):
    cfg, _, tmp, art = pipeline
    out = tmp / "report_bad"
    with pytest.raises(ArtifactError, match=re.escape(str(art["observations"]))):
        report(cfg, out, observations=art["observations"], forecast=art["observations"])
    assert not (out / "index.html").exists()
    assert not list(tmp.glob(".report_bad*"))


def test_failed_report_leaves_the_previous_one_intact(pipeline):
    cfg, _, tmp, art = pipeline
    out = tmp / "report_keep"
    report(cfg, out, observations=art["observations"])
    before = file_sha256(out / "index.html")
    with pytest.raises(ArtifactError):
        report(cfg, out, observations=art["observations"], surrogate=art["truth"])
    assert file_sha256(out / "index.html") == before


def test_indicator_of_a_record_ignores_missing_samples(pipeline):
    from twinmon.observations import read_observations
    cfg, _, _, art = pipeline
    ind = Indicator.from_config(cfg)
    obs = read_observations(art["observations"], cfg.model.output.name)
    out = obs.output_of("Park")[:1].copy()
    ref = indicator_rows(ind, obs.time, out)[0]
    out[0, -3] = np.nan                      # a late sample, far after the crossing
    assert indicator_rows(ind, obs.time, out)[0] == ref
    assert 5 < ref < ind.limit


def test_html_speaks_the_configs_words(pipeline, full):
    cfg, _, _, art = pipeline
    summary, out = full
    text = (out / "index.html").read_text()
    ind = Indicator.from_config(cfg)
    captions = " ".join(f["caption"] + " " + f["title"] for f in summary.figures)
    for words in (cfg.model.output.label, cfg.model.output.units, ind.name, ind.label,
                  f"{ind.limit:g} {ind.units}"):
        assert words in text, words
    assert f"measured {cfg.model.output.label}" in captions.lower()
    # The report's own words are neutral ("start-up" may still come from the config's
    # diagnose windows).
    assert "start-up" not in captions.lower()


def test_cli_report_finds_artifacts_in_workdir(pipeline):
    from click.testing import CliRunner

    from twinmon.cli import main
    cfg, cfg_path, tmp, art = pipeline
    res = CliRunner().invoke(main, ["report", "-c", str(cfg_path), "--workdir", str(tmp),
                                    "--observations", str(art["observations"]),
                                    "-o", str(tmp / "cli_report"), "--json"])
    assert res.exit_code == 0, res.output
    data = json.loads(res.stdout)
    assert data["index"] == str(tmp / "cli_report" / "index.html")
    assert Path(data["index"]).exists()
    for role in ("simulations", "surrogate", "posterior", "forecast", "gap"):
        assert (role in data["artifacts"]) == (art[role] is not None)
    assert "truth" not in data["artifacts"]


def test_cli_report_fails_on_a_workdir_that_is_missing_or_empty(pipeline, tmp_path):
    from click.testing import CliRunner

    from twinmon.cli import main
    from twinmon.errors import ArtifactError
    _, cfg_path, _, _ = pipeline
    empty = tmp_path / "empty"
    empty.mkdir()
    for folder in (tmp_path / "no_such_folder", empty):
        res = CliRunner().invoke(main, ["report", "-c", str(cfg_path), "--workdir", str(folder)])
        assert res.exit_code == ArtifactError.exit_code, res.output
        lines = res.stderr.strip().splitlines()
        assert len(lines) == 1 and str(folder) in lines[0] and "artifact error" in lines[0]
        assert not (folder / "report").exists()


DCDRIVE = CONFIGS / "dcdrive_fleet.yaml"


def _dcdrive_config():
    """The DC drive example's config, or None when it is not there (or does not load)."""
    if not DCDRIVE.exists():
        return None
    try:
        return load_config(DCDRIVE)
    except Exception:  # noqa: BLE001  (the example is being written: skip, do not fail)
        return None


@pytest.mark.skipif(_dcdrive_config() is None, reason="configs/dcdrive_fleet.yaml not available")
def test_report_of_another_machine_speaks_its_words(tmp_path):
    """The whole chain on the DC drive (a mean speed over a window, unsafe below a limit): the
    report names its output and indicator and nothing of the pump."""
    from twinmon.calibrate import calibrate
    from twinmon.fabricate import fabricate
    from twinmon.forecast import forecast
    from twinmon.reduce import reduce
    from twinmon.simulate import simulate
    cfg = load_config(write_yaml(tmp_path / "dc.yaml", {
        "extends": str(DCDRIVE),
        "simulate": {"train_size": 24, "test_size": 8, "executor": "serial"},
        "calibrate": {"chains": 2, "samples": 200, "burn_in": 50, "workers": 1, "ess_warn": 100.0, "max_extensions": 1},
        "forecast": {"samples": 200},
        "fabricate": {"years": 4},
    }))
    art = {"observations": tmp_path / "obs.h5", "truth": tmp_path / "truth.h5",
           "simulations": tmp_path / "sims.h5", "surrogate": tmp_path / "sur.h5",
           "posterior": tmp_path / "post.h5", "forecast": tmp_path / "fc.h5"}
    simulate(cfg, art["simulations"])
    reduce(cfg, art["simulations"], art["surrogate"])
    fabricate(cfg, art["observations"], art["truth"])
    calibrate(cfg, art["surrogate"], art["observations"], art["posterior"])
    forecast(cfg, art["posterior"], art["surrogate"], art["forecast"])
    out = tmp_path / "report"
    s = report(cfg, out, **art)

    assert {k for k, v in s.sections.items() if v == "rendered"} == {
        "observations", "surrogate", "calibration", "forecast"}
    assert {"fig2_last_transients", "fig3_indicator_history", "fig5_surrogate",
            "fig9_indicator_forecast"} <= {f["name"] for f in s.figures}
    text = (out / "index.html").read_text()
    ind = Indicator.from_config(cfg)
    out_spec = cfg.model.output
    for words in (out_spec.label, out_spec.units, f"Measured {out_spec.label}", ind.name,
                  ind.label, f"{ind.limit:g} {ind.units}", f"{ind.name} is below"):
        assert words in text, words
    words_only = re.sub(r'src="data:image/png;base64,[^"]*"', "", text)   # base64 is not words
    for words in ("kg/s", "mass flow", "t90", "nominal flow", "start-up transient"):
        assert words not in words_only, words
    data = json.loads((out / "summary.json").read_text())
    assert data["indicator"]["name"] == ind.name and data["indicator"]["sense"] == -1
    assert data["output"]["label"] == out_spec.label
    assert data["surrogate"]["max_range_error"] >= data["surrogate"]["mean_range_error"] > 0
    for u in data["units"].values():
        assert u["last_indicator"] is not None        # a mean speed is always defined
        assert u["last_indicator_text"].endswith(ind.units)


def test_a_report_is_up_to_date_while_what_it_reads_is_the_same(pipeline, full, tmp_path):
    """``twinmon run``'s test (``is_up_to_date``): the same artifacts and config, however
    many processes drew it; not with another setting the report reads, another artifact,
    or a file of the report gone."""
    import shutil

    from twinmon.report import is_up_to_date
    _, cfg_path, tmp, art = pipeline
    _, out = full
    same = is_up_to_date(load_config(cfg_path, ["report.workers=1"]), out, art)
    assert same is not None and same["made_from"]["inputs"].keys() == {
        k for k, v in art.items() if v is not None}
    assert is_up_to_date(load_config(cfg_path, ["report.detail_units=2"]), out, art) is None
    assert is_up_to_date(load_config(cfg_path), out, {**art, "truth": None}) is None
    copy = tmp_path / "copy"
    shutil.copytree(out, copy)
    assert is_up_to_date(load_config(cfg_path), copy, art) is not None
    next((copy / "figures").iterdir()).unlink()
    assert is_up_to_date(load_config(cfg_path), copy, art) is None
    # A summary.json edited or damaged into another shape: stale, not a traceback.
    edited = {**json.loads((out / "summary.json").read_text()), "figures": ["x"]}
    for bad in (json.dumps(edited), "[1, 2]", "{"):
        (copy / "summary.json").write_text(bad)
        assert is_up_to_date(load_config(cfg_path), copy, art) is None


def test_figures_drawn_by_worker_processes_are_the_same_bytes(pipeline, full):
    # report.workers > 1 pickles each figure to a pool that lays it out and writes it; the
    # PNGs (and so the page's images) must not depend on it. Digests, not bytes: on a
    # mismatch the message names the figures (pytest's diff of the bytes took over an hour).
    # The pool also reads the units' statistics, in one run of units per worker: the
    # summaries must not depend on it either. The full report's pool had two workers.
    _, cfg_path, tmp, art = pipeline
    made, said = {}, {}
    out = tmp / "report_w1"
    s = report(load_config(cfg_path, ["report.workers=1"]), out, **art)
    made[1] = {f["name"]: file_sha256(f["path"]) for f in s.figures}
    said[1] = (out / "summary.json").read_text().replace(str(out), "OUT")
    s, out = full
    made[2] = {f["name"]: file_sha256(f["path"]) for f in s.figures}
    said[2] = (out / "summary.json").read_text().replace(str(out), "OUT")
    assert len(made[1]) >= 5
    assert [n for n in made[1] if made[2].get(n) != made[1][n]] == []
    assert said[1] == said[2]


def test_a_pickled_figure_keys_its_transforms_by_this_processs_ids(tmp_path):
    # matplotlib restores a transform's parents keyed by the ids they had where the figure
    # was pickled; a transform made while drawing at such an address then unhooks a parent,
    # which draws stale (seen as a line cut short in a worker process). The loader re-keys.
    import gc
    import pickle

    from matplotlib.transforms import TransformNode

    from twinmon.report.common import Figures, load_pickled_figure
    fig = Figures(tmp_path).new(4, 3)
    ax = fig.add_subplot()
    ax.semilogy([0, 1, 2], [1, 10, 100], "s-")
    ax.boxplot([[1, 2, 3], [2, 3, 4]])
    ax.legend(["a"], loc="best")
    blob = pickle.dumps(fig, protocol=pickle.HIGHEST_PROTOCOL)
    loaded = load_pickled_figure(blob)
    stale = [(k, id(r())) for node in gc.get_objects()
             if issubclass(type(node), TransformNode)
             for k, r in getattr(node, "_parents", {}).items()
             if r() is not None and id(r()) != k]
    assert stale == []
    loaded.savefig(tmp_path / "x.png")
    assert (tmp_path / "x.png").read_bytes().startswith(PNG_MAGIC)


def test_a_figure_that_does_not_pickle_is_written_in_the_process(tmp_path):
    from matplotlib.ticker import FuncFormatter

    from twinmon.executors import closing_pool, start_pool
    from twinmon.report.common import Figures
    with closing_pool(start_pool(1), RuntimeError("worker died")) as pool:
        figs = Figures(tmp_path, pool)
        fig = figs.new(3, 2)
        ax = fig.add_subplot()
        ax.plot([0, 1], [0, 1])
        ax.xaxis.set_major_formatter(FuncFormatter(lambda v, _: f"{v:.1f}"))   # no pickle
        figs.save(fig, "local", "observations", "A local formatter", "")
        fig2 = figs.new(3, 2)
        fig2.add_subplot().plot([0, 1], [1, 0])
        figs.save(fig2, "plain", "observations", "Plain", "")
        figs.finish()
    for name in ("local", "plain"):
        assert (tmp_path / f"{name}.png").read_bytes().startswith(PNG_MAGIC)


@pytest.mark.skipif(_dcdrive_config() is None, reason="configs/dcdrive_fleet.yaml not available")
def test_a_withheld_unit_keeps_its_true_failure_year(tmp_path):
    """A prognosis withheld by the fit gate still has a true failure year in forecast.h5
    (fabricated data): the report shows it, as it does for a unit with a prognosis. The gate
    is made to withhold every unit here: a year "misses the plant" when its residual RMS
    passes the noise's and its chi-square or Ljung-Box test rejects at 0.999, which about
    half of a unit's years do, and one such year withholds."""
    from twinmon.calibrate import calibrate
    from twinmon.fabricate import fabricate
    from twinmon.forecast import forecast, read_forecast
    from twinmon.reduce import reduce
    from twinmon.simulate import simulate
    cfg = load_config(write_yaml(tmp_path / "dc.yaml", {
        "extends": str(DCDRIVE),
        "simulate": {"train_size": 24, "test_size": 4, "executor": "serial"},
        "calibrate": {"chains": 2, "samples": 150, "burn_in": 50, "workers": 1,
                      "ess_warn": 50.0, "max_extensions": 0,
                      "fit_min_rms": 1.0, "fit_alpha": 0.999},
        "forecast": {"samples": 150, "withhold_years": 1}}))
    art = {"observations": tmp_path / "obs.h5", "truth": tmp_path / "truth.h5",
           "simulations": tmp_path / "sims.h5", "surrogate": tmp_path / "sur.h5",
           "posterior": tmp_path / "post.h5", "forecast": tmp_path / "fc.h5"}
    simulate(cfg, art["simulations"])
    reduce(cfg, art["simulations"], art["surrogate"])
    fabricate(cfg, art["observations"], art["truth"])
    calibrate(cfg, art["surrogate"], art["observations"], art["posterior"])
    forecast(cfg, art["posterior"], art["surrogate"], art["forecast"], art["truth"])
    fc = read_forecast(art["forecast"])
    withheld = {u: f for u, f in fc.units.items() if f.status == "withheld" and not f.forced}
    true_years = {u: f.true_failure_year for u, f in withheld.items()
                  if f.has_truth and f.true_failure_year is not None}
    assert true_years, {u: (f.status, f.true_failure_year) for u, f in fc.units.items()}
    s = report(cfg, tmp_path / "report", **art)
    data = json.loads((tmp_path / "report" / "summary.json").read_text())
    for unit, year in true_years.items():
        assert s.units[unit].status == "withheld"
        assert s.units[unit].true_failure_year == year
        assert data["units"][unit]["true_failure_year"] == year
    html = (tmp_path / "report" / "index.html").read_text()
    for year in true_years.values():
        assert f"true failure year (fabricated data): {year}" in html


def test_a_narrow_figure_wraps_its_title_inside_the_figure(tmp_path):
    """Figure 8 of a one-input model is 5.2 in wide; its title, written for several panels,
    was clipped at both edges. Figures.save wraps it to the width."""
    from twinmon.report.common import Figures
    figs = Figures(tmp_path)
    fig = figs.new(4.6 * 1 + 0.6, 3.6)
    fig.subplots(1, 1)
    fig.suptitle("Forecast distributions of the degradation inputs (units with a detected "
                 "fault)\ngrey background: outside the surrogate's training box (the FMU is "
                 "run there)")
    figs.save(fig, "narrow", "forecast", "t", "c")
    renderer = fig.canvas.get_renderer()
    box = fig._suptitle.get_window_extent(renderer)
    assert box.x0 >= 0 and box.x1 <= fig.bbox.width, (box, fig.bbox)
    assert "units with a detected fault" in fig._suptitle.get_text().replace("\n", " ")


def test_candidates_hidden_alike_on_every_unit_are_said_once():
    from twinmon.report.summary import diagnose_lines, shared_hidden
    h = {"tacho.gain": {"value": 1.05, "gap": 0.4, "visible": False, "channel": "armature.i",
                        "channel_score": 9.0}}
    other = {"load.extra": {"value": 0.2, "gap": 0.3, "visible": False, "channel": None,
                            "channel_score": 0.0}}
    same = [{"hidden": h, "groups": []}, {"hidden": dict(h), "groups": []}]
    assert shared_hidden(same) == h
    assert diagnose_lines(same[0], hidden=False) == []
    assert any("tacho.gain" in x for x in diagnose_lines(same[0]))
    assert shared_hidden([same[0], {"hidden": other, "groups": []}]) == {}
    assert shared_hidden([same[0], None]) == {}
    assert shared_hidden(same[:1]) == {}


def test_a_healthy_units_failure_year_says_whether_its_centre_or_its_spread_reaches_it():
    from twinmon.forecast.plan import no_fault_due
    years = np.arange(11, 18)
    assert no_fault_due(years, np.linspace(0.0, 0.7, 7), 0.05) == (
        "its trend reaches the limit, though no input's slope over its record is proven "
        "beyond normal ageing")
    why = no_fault_due(years, np.linspace(0.0, 0.3, 7), 0.05)
    assert why.startswith("no fault is seen, but the forecast's spread reaches the limit")
    assert "P(unsafe) above 5 %" in why


def test_a_gap_fleet_with_units_the_fleet_lacks_gets_its_own_colours(pipeline, tmp_path):
    """Diagnose run on another file than the report's observations (run's
    --gap-observations), with a unit the observed fleet does not have: the diagnose figures
    draw it in a colour of its own instead of failing on a missing colour."""
    from ..conftest import first_years
    cfg, _, _, art = pipeline
    if art["gap"] is None:
        pytest.skip("diagnose is not built")
    obs = first_years(art["observations"], tmp_path / "two.h5", 4, units=["Park", "Colt"])
    s = report(cfg, tmp_path / "out", observations=obs, gap=art["gap"])
    assert s.sections["diagnose"] == "rendered"
    assert "Monk" in (tmp_path / "out" / "index.html").read_text()


def test_a_gap_of_another_file_is_not_merged_when_the_observations_are_not_given(
        pipeline, tmp_path):
    """report --workdir without --observations, after run --gap-observations: the gap
    artifact diagnosed another file than the posterior was calibrated from, so its units
    (here Monk's first three years, standing for a gap fleet's unit of the same name) are
    other records, not the fleet's units."""
    from twinmon.diagnose import diagnose

    from ..conftest import first_years
    cfg, _, _, art = pipeline
    if art["posterior"] is None:
        pytest.skip("calibrate is not built")
    other = first_years(art["observations"], tmp_path / "other.h5", 3, units=["Monk"])
    diagnose(cfg, other, tmp_path / "gap.h5", workers=1)
    out = tmp_path / "out"
    report(cfg, out, posterior=art["posterior"], forecast=art["forecast"],
           gap=tmp_path / "gap.h5")
    data = json.loads((out / "summary.json").read_text())
    assert data["units"]["Monk"]["diagnose"] is None
    assert "This section diagnoses" in (out / "index.html").read_text()



def test_surrogate_figure_of_three_long_named_inputs_keeps_its_titles_inside(tmp_path):
    """Figure 5's legend names each drawn test run by its inputs: with three inputs of long
    names the two-column legend was wider than its panel, the layout pushed the error panel
    off the figure and its title was clipped at the right edge."""
    from types import SimpleNamespace

    from twinmon.report.common import Figures, Words
    from twinmon.report.fig_surrogate import fig_surrogate
    cfg = load_config(DCDRIVE)
    time = cfg.model.output.times.times
    X = np.array([[23.1, 115.0, 2.82], [32.2, 74.4, 4.75], [35.2, 20.4, 6.03],
                  [34.9, 94.4, 27.3], [30.0, 60.0, 10.0]])
    Y = 250.0 + 40.0 * (1 - np.exp(-time[None, :] / (0.2 + 0.05 * np.arange(5)[:, None])))
    sur = SimpleNamespace(
        input_names=["element_resistance", "element_conductance", "insulation_loss"],
        predict_with_var=lambda x: (Y[: len(x)] * 1.001, np.full((len(x), time.size), 0.01)))
    sims = SimpleNamespace(ok={"test": np.ones(len(X), bool)}, X={"test": X}, Y={"test": Y},
                           time=time)
    drawn = []

    class Kept(Figures):
        def save(self, fig, *args):
            drawn.append(fig)
            super().save(fig, *args)

    fig_surrogate(Kept(tmp_path), SimpleNamespace(surrogate=sur, sims=sims,
                                                  words=Words.from_config(cfg)))
    (fig,) = drawn
    renderer = fig.canvas.get_renderer()
    for ax in fig.axes:
        for art in (ax.title, ax.get_legend()):
            box = art.get_window_extent(renderer)
            assert box.x0 >= 0 and box.x1 <= fig.bbox.width, (art, box, fig.bbox)


def test_a_prognosis_withheld_at_the_box_is_not_called_a_misfit():
    """A unit withheld because its estimates sit on the design box's edge, while the twin
    fits its data, was titled 'prognosis withheld: the twin misses the plant' in the unit
    table and on figures 7-9, beside a reason saying the twin fits."""
    from twinmon.report.common import state_words
    from twinmon.report.unit_summary import UnitSummary
    edge = ("prognosis withheld: the estimates of insulation_loss sit on the design box's "
            "low edge (31 % of the posterior in year 9 within 2 % of the range of 0.5 W/K) "
            "from year 1: the plant needs, or nearly needs, inputs beyond the twin's box; "
            "widen model.inputs.insulation_loss.low or run 'twinmon diagnose'")
    misfit = ("prognosis withheld: the twin misses the plant by 3.1 noise sd in the heating "
              "window (residual RMS 2.0 sd in year 4; 3 of 6 years miss) from year 4; run "
              "'twinmon diagnose'")
    assert "misses" not in state_words("withheld", edge)
    assert "box" in state_words("withheld", edge)
    assert "misses the plant" in state_words("withheld", misfit)
    assert "misses the plant" in state_words("withheld")
    s = UnitSummary(name="Ash", status="withheld", status_reason=edge, root_cause="withheld")
    assert "misses" not in s.status_words and "box" in s.status_words
    s = UnitSummary(name="Ash", status="withheld", status_reason=misfit, root_cause="withheld")
    assert "misses the plant" in s.status_words


def test_figure_9_does_not_say_no_failure_for_a_withheld_prognosis():
    """A withheld unit has no failure year; figure 9 titled it 'no failure by year 17' above
    P(unsafe) of 67-100 % in the years drawn under the title."""
    from types import SimpleNamespace

    from twinmon.report.fig_forecast import failure_words
    held = SimpleNamespace(status="withheld", forced=False, failure_year=None)
    assert "no failure by" not in failure_words(held, 17)
    assert "withheld" in failure_words(held, 17)
    forced = SimpleNamespace(status="withheld", forced=True, failure_year=13)
    assert failure_words(forced, 17) == "fails in year 13"
    # Past the limit in its last recorded years: since when, not the next year's date.
    past = SimpleNamespace(status="ok", forced=False, failure_year=11, unsafe_since=8)
    assert failure_words(past, 17) == "unsafe since year 8"
    ok = SimpleNamespace(status="ok", forced=False, failure_year=None)
    assert failure_words(ok, 17) == "no failure by year 17"


def test_figure_8_axis_follows_the_bulk_of_the_draws_not_a_few_far_ones():
    """Three far draws in 2000 (a wear shape extended far: the water heater's conductance
    drawn at 870 W/K beside a bulk at 60-150) set figure 8's axis to 0-900 and squeezed
    the histograms into a bin or two; the axis now leaves out the extreme 1 % at each end
    and keeps the true values in view."""
    from twinmon.report.fig_forecast import shown_range
    rng = np.random.default_rng(3)
    bulk = rng.normal(100.0, 15.0, 2000)
    bulk[:3] = [870.0, 640.0, 0.0]
    lo, hi = shown_range([bulk, bulk + 5.0], marks=[95.0, 170.0])
    assert 40.0 < lo < 70.0 and 165.0 < hi < 190.0, (lo, hi)


def test_a_prognosis_withheld_at_the_box_is_not_a_disagreement_with_diagnose(pipeline):
    """Withheld because the estimates sit on the box's edge (the twin fits), with no gap
    found by diagnose: the two stages agree. The summary said 'diagnose found no
    significant gap although calibration finds the twin missing the plant'."""
    import dataclasses

    from twinmon.report.load import load, observed_indicator
    from twinmon.report.summary import unit_summary
    cfg, _, _, art = pipeline
    if art["forecast"] is None or art["gap"] is None:
        pytest.skip("forecast or diagnose is not built")
    inp = load(cfg, {k: art[k] for k in ("observations", "forecast", "gap")})
    unit = "Park"
    edge = ("prognosis withheld: the estimates of motor_damping sit on the design box's low "
            "edge (31 % of the posterior in year 4 within 2 % of the range of 4) from year 1: "
            "the plant needs, or nearly needs, inputs beyond the twin's box; widen "
            "model.inputs.motor_damping.low or run 'twinmon diagnose'")
    uf = inp.forecast.units[unit]
    uf.status, uf.status_reason, uf.forced = "withheld", edge, False
    inp.gap.units[unit] = dataclasses.replace(inp.gap.units[unit], verdict="none")
    s = unit_summary(unit, inp, observed_indicator(inp))
    assert "although calibration finds the twin missing the plant" not in s.confidence
    misfit = ("prognosis withheld: the twin misses the plant by 3.1 noise sd in the rise "
              "window (residual RMS 2.0 sd in year 4; 3 of 4 years miss) from year 2; run "
              "'twinmon diagnose'")
    uf.status_reason = misfit
    s = unit_summary(unit, inp, observed_indicator(inp))
    assert "although calibration finds the twin missing the plant" in s.confidence


def test_a_unit_unsafe_already_is_said_so_not_given_next_year():
    """A unit whose last recorded years are past the limit was told "fails in year 11" (the
    year after the record, only the year to act by); a withheld one measured past the limit
    said nothing of it. The summary now says since when, from the posterior and from the
    recorded transients themselves."""
    from twinmon.report.unit_summary import UnitSummary, trailing_run
    assert trailing_run([1, 2, 3, 5, 6], [False, True, False, True, True]) == 5
    assert trailing_run([1, 2, 3], [True, True, True]) == 1
    assert trailing_run([1, 2, 3], [True, True, False]) is None
    assert trailing_run([], []) is None
    s = UnitSummary(name="Ash", status="ok", root_cause="bearing", failure_year=11,
                    p_unsafe=1.0, last_year=10, horizon_end=17, unsafe_since=6,
                    p_unsafe_last=0.98, measured_unsafe_since=7)
    assert s.time_to_failure == ("unsafe since year 6 (P(unsafe) 98 % in 10; measured unsafe "
                                 "since year 7)")
    assert s.as_dict()["unsafe_since"] == 6 and s.as_dict()["measured_unsafe_since"] == 7
    # Past the limit at under even odds: "possibly".
    s = UnitSummary(name="Ash", status="ok", root_cause="bearing", failure_year=11,
                    p_unsafe=0.2, last_year=10, horizon_end=17, unsafe_since=10,
                    p_unsafe_last=0.13)
    assert s.time_to_failure == "possibly unsafe since year 10 (P(unsafe) 13 % in 10)"
    from twinmon.report.fleet import failure_cell
    assert failure_cell(s) == "possibly unsafe since 10"
    edge = ("prognosis withheld: the estimates lean on the design box's edge from year 1; "
            "widen model.inputs.friction.high")
    s = UnitSummary(name="Ash", status="withheld", status_reason=edge, root_cause="withheld",
                    measured_unsafe_since=1)
    assert s.time_to_failure.endswith("; measured unsafe since year 1")
    s = UnitSummary(name="Ash", status="ok", root_cause="healthy", horizon_end=17,
                    p_unsafe=0.0)
    assert s.time_to_failure == "no failure by year 17 (max P(unsafe) 0 %)"
    # The fleet overview's cells and reasons say it too.
    from twinmon.report.fleet import failure_cell, risk_reasons
    now = UnitSummary(name="Ash", status="ok", root_cause="bearing", failure_year=11,
                      last_year=10, horizon_end=17, unsafe_since=6, p_unsafe_max=1.0)
    assert failure_cell(now) == "unsafe since 6"
    assert risk_reasons(now, 0.05)[0] == "unsafe since year 6"
    held = UnitSummary(name="Ash", status="withheld", status_reason=edge,
                       root_cause="withheld", measured_unsafe_since=1)
    assert failure_cell(held) == "withheld, measured unsafe since 1"
    assert "measured unsafe since year 1" in risk_reasons(held, 0.05)


def test_several_faults_are_named_by_their_components():
    """A verdict on several components names them (a model of three components: 'both'
    alone would not say which two)."""
    from twinmon.forecast.attribution import attribute
    from twinmon.report.common import state_words
    assert state_words("both", "", ["spindle", "vee-belt"]) == "spindle and vee-belt faults"
    assert state_words("both") == "several faults"
    assert state_words("pump", "", ["pump"]) == "pump fault"
    # The attribution records the components it names.
    from twinmon.forecast.trend import Trend
    rng = np.random.default_rng(0)
    draws = np.column_stack([rng.normal(2.0, 0.1, 4000), rng.normal(-0.3, 0.01, 4000),
                             rng.normal(0.0, 0.01, 4000)])
    tl = [Trend(0.0, float(m), 0.1, (0, 0), 0.1, 10, 5.5, 82.5) for m in draws.mean(axis=0)]
    att = attribute(tl, ["a", "b", "c"], ["belt", "spindle", "filter"], np.eye(3) * 1e-4,
                    np.zeros(3), np.array([0.25, 0.03, 0.03]), [+1, -1, +1], 0.8,
                    rng, draws=draws)
    assert att.verdict == "both" and att.named == ["belt", "spindle"], att


def test_recorded_maintenance_is_said_in_the_report():
    """A repair the user recorded (events add, import-csv) is in the unit's reasons, with
    its note; from the posterior's copy when the observations are not given."""
    from types import SimpleNamespace
    from twinmon.observations import Event, Observations, UnitObservations
    from twinmon.report.summary import recorded_events
    u = UnitObservations(np.arange(1, 11), {"speed": np.ones((10, 3))}, {"speed": 3.0},
                         [Event(8, "bearing", note="WO 77")])
    obs = Observations(np.array([0.1, 0.2, 0.3]), {"D": u}, output="speed")
    assert recorded_events(SimpleNamespace(obs=obs), "D", None) == [
        "bearing replaced in year 8 (WO 77) as recorded: its trend restarts there"]
    post = SimpleNamespace(events=[(6, "winding", "repaired")])
    assert recorded_events(SimpleNamespace(obs=None), "D", post) == [
        "winding repaired in year 6 as recorded: its trend restarts there"]
    assert recorded_events(SimpleNamespace(obs=None), "D", None) == []
