"""The report's figures for vehicle research (issue 43): the 3D figure to scale with paths drawn
under an obstacle only where it hides them, the snapshot labels off the goal marker, the settle
time on the error figures, links.png without all-zero counters, and SVG/PDF on request
(``zenswarm report --format``, ``up --report-format``). Figures are inspected as matplotlib
draws them (the Figure handed to ``figures._save``, bridge/reports/figures.py)."""

from __future__ import annotations

import numpy as np
import pytest
from test_report import SWARM, _toml, flight, recording  # noqa: F401  (fixtures)

from zenswarm.bridge.reports import figures as report_figures
from zenswarm.bridge.reports import report
from zenswarm.compose.cli import main as cli_main
from zenswarm.scenario.config import scenario_to_dict


@pytest.fixture
def figures(monkeypatch):
    """The Figures the report saves, by file name (stem)."""
    got: dict = {}
    save = report_figures._save

    def keep(fig, path, formats=("png",)):
        got[path.stem] = fig
        return save(fig, path, formats)

    monkeypatch.setattr(report_figures, "_save", keep)
    return got


def test_3d_figure_is_to_scale_and_paths_go_under_obstacles_only_where_hidden(flight, tmp_path, figures):  # noqa: F811
    sc, sim = flight
    report.plot_trajectories(sim.series, sc, tmp_path / "trajectories_3d.png")
    fig = figures["trajectories_3d"]
    ax = next(a for a in fig.axes if a.name == "3d")
    spans = np.array([np.ptp(ax.get_xlim()), np.ptp(ax.get_ylim()), np.ptp(ax.get_zlim())])
    box = np.asarray(ax.get_box_aspect(), dtype=float)
    np.testing.assert_allclose(box / box.max(), spans / spans.max(), rtol=1e-6)  # one metre as long on x, y and z
    assert ax.computed_zorder is False
    surfaces = [c for c in ax.collections if type(c).__name__ == "Poly3DCollection"]
    assert surfaces and {c.get_zorder() for c in surfaces} == {2}
    lines = [ln for ln in ax.get_lines() if np.isfinite(np.asarray(ln.get_data_3d(), dtype=float)).any()]
    under = [ln for ln in lines if ln.get_zorder() < 2]
    over = [ln for ln in lines if ln.get_zorder() > 2]
    assert over and len(over) == len(lines) - len(under)
    # the hidden parts are exactly the points behind an obstacle from the figure's view
    for ln in under:
        p = np.asarray(ln.get_data_3d(), dtype=float).T
        assert report.hidden_behind_obstacles(p, sc, *report.VIEW_3D)[np.isfinite(p).all(axis=1)].all()


def test_hidden_behind_obstacles_is_what_a_viewer_sees():
    """A point beyond an obstacle on the line of sight is hidden; in front of it, beside it or
    above its cap, not (orthographic view from the figure's elevation and azimuth)."""
    from types import SimpleNamespace

    ob = SimpleNamespace(center=(0.0, 0.0, 0.0), radius=1.0, height=4.0)
    sc = SimpleNamespace(obstacles=[ob])
    elev, azim = report.VIEW_3D
    e, a = np.radians(elev), np.radians(azim)
    eye = np.array([np.cos(e) * np.cos(a), np.cos(e) * np.sin(a), np.sin(e)])
    right = np.array([-np.sin(a), np.cos(a), 0.0])
    mid = np.array([0.0, 0.0, 2.0])
    pts = np.array([mid - 5 * eye, mid + 5 * eye, mid - 5 * eye + 3 * right, [0.0, 0.0, 20.0], [np.nan, 0, 0]])
    assert report.hidden_behind_obstacles(pts, sc, elev, azim).tolist() == [True, False, False, False, False]


def test_snapshot_labels_are_not_on_the_goal_marker(flight, tmp_path, figures):  # noqa: F811
    sc, sim = flight
    from zenswarm.scenario.config import scenario_from_dict

    doc = scenario_to_dict(sc)  # the 3 s flight ends far from the goal: put the goal where the leader ends (the last snapshot)
    doc["leader"]["goal"] = [float(x) for x in sim.series.q0[-1]]
    sc2 = scenario_from_dict(doc)
    report.plot_trajectories(sim.series, sc2, tmp_path / "trajectories_3d.png")
    fig = figures["trajectories_3d"]
    top = next(a for a in fig.axes if a.name != "3d")
    from matplotlib.backends.backend_agg import FigureCanvasAgg

    canvas = FigureCanvasAgg(fig)
    canvas.draw()
    renderer = canvas.get_renderer()
    gx, gy = top.transData.transform(sc2.leader.goal[:2])
    half = report.GOAL_MS / 2 * fig.dpi / 72  # the star's half width, px
    labels = [t for t in top.texts if t.get_text().endswith(" s")]
    assert labels
    for t in labels:
        bb = t.get_window_extent(renderer)
        apart = bb.x1 < gx - half or bb.x0 > gx + half or bb.y1 < gy - half or bb.y0 > gy + half
        assert apart, f"label {t.get_text()!r} {bb} on the goal marker at ({gx:.0f}, {gy:.0f})"


def test_error_figures_mark_the_settle_time(flight, tmp_path, figures):  # noqa: F811
    sc, sim = flight
    report.plot_formation_errors(sim.series, sc, tmp_path / "formation_errors.png")
    report.plot_vehicle_formation_errors(sim.series, sc, tmp_path / "formation_errors_vehicles.png")
    report.plot_tracking_errors(sim.series, sc, tmp_path / "tracking_errors.png")
    settle = sc.timing.settle_time_s
    for name in ("formation_errors", "formation_errors_vehicles", "tracking_errors"):
        for ax in figures[name].axes:
            xs = [ln.get_xdata() for ln in ax.get_lines() if len(ln.get_xdata()) == 2 and ln.get_xdata()[0] == ln.get_xdata()[1]]
            assert any(float(x[0]) == settle for x in xs), (name, ax.get_title())
        assert f"settle time {settle:g} s" in figures[name]._suptitle.get_text()


def test_links_figure_draws_only_the_nonzero_counters(flight, recording, tmp_path, figures):  # noqa: F811
    fl = report.flight_from_recording(report.load_recording(recording[0]))
    faults = report_figures._fault_counters(fl)
    nonzero = [lab for lab, v in faults if v]
    assert 0 < len(nonzero) < len(faults)  # the recording has both
    report.plot_links(fl, tmp_path / "links.png")
    fig = figures["links"]
    ax = fig.axes[1]
    assert [t.get_text() for t in ax.get_yticklabels()] == nonzero
    assert any(f"{len(faults) - len(nonzero)} more counters at zero" in t.get_text() for t in ax.texts)
    assert fig.get_size_inches()[1] <= 0.2 * max(len(fl.message_counts), len(nonzero)) + 1.3 + 1e-9


def test_report_writes_svg_and_pdf_on_request_and_refuses_an_unknown_format(flight, tmp_path, capsys):  # noqa: F811
    sc, sim = flight
    sim.series.save(str(tmp_path / "timeseries.npz"))
    scen = tmp_path / "scenario.toml"
    scen.write_text(_toml(scenario_to_dict(sc)))
    out = tmp_path / "plots"
    base = ["report", "--series", str(tmp_path / "timeseries.npz"), "--scenario", str(scen), "--out", str(out)]
    with pytest.raises(SystemExit) as e:
        cli_main([*base, "--format", "png,jpg"])
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "--format" in err and "'jpg'" in err, err
    assert not out.exists(), "nothing written"
    assert cli_main([*base, "--format", "svg,pdf"]) == 0
    printed = capsys.readouterr().out.split()
    stems = [n.removesuffix(".png") for n in report.FIGURES if n != "links.png"]
    assert printed == [str(out / f"{s}.{x}") for s in stems for x in ("svg", "pdf")]
    for s in stems:
        assert (out / f"{s}.svg").read_text().lstrip().startswith(("<?xml", "<svg"))
        assert (out / f"{s}.pdf").read_bytes()[:5] == b"%PDF-"
        assert not (out / f"{s}.png").exists()


def test_up_report_format_is_checked_before_anything_starts(tmp_path, capsys):
    from swarmtest import ROOT

    scenario = ROOT / "compose" / "scenarios" / "paper_example1.toml"
    with pytest.raises(SystemExit) as e:
        cli_main(["up", str(scenario), "--out", str(tmp_path / "o"), "--record", str(tmp_path / "f.mcap"), "--report",
                  "--report-format", "tiff"])  # fmt: skip
    assert e.value.code == 2
    err = capsys.readouterr().err
    assert "--report-format" in err and "'tiff'" in err, err
    assert not (tmp_path / "o").exists()


def test_commands_figure_shows_commanded_against_achieved_per_uav(flight, tmp_path, figures):  # noqa: F811
    """commands.png: a row per UAV; the commanded thrust and attitude are the series' ``thrust``
    and ``rpy_cmd`` (the controller's command, not the measured attitude ``rpy``), beside the
    thrust the motion implies and the measured attitude."""
    sc, sim = flight
    ts = sim.series
    assert np.isfinite(ts.rpy_cmd).all() and not np.array_equal(ts.rpy_cmd, ts.rpy)
    report.plot_commands(ts, sc, tmp_path / "commands.png")
    axes = np.asarray(figures["commands"].axes).reshape(sc.n, 4)
    for i in range(sc.n):
        np.testing.assert_array_equal(axes[i, 0].get_lines()[0].get_ydata(), ts.thrust[:, i])
        for c in range(3):
            cmd, measured = axes[i, c + 1].get_lines()[:2]
            np.testing.assert_array_equal(cmd.get_ydata(), np.degrees(ts.rpy_cmd[:, i, c]))
            np.testing.assert_array_equal(measured.get_ydata(), np.degrees(ts.rpy[:, i, c]))
    # the implied thrust of a hovering vehicle is its weight: the plotted curve ends near m g
    from zenswarm.vehicle.params import QuadParams

    qp = QuadParams.from_vehicle(sc.vehicle)
    implied = axes[0, 0].get_lines()[1].get_ydata()
    assert abs(implied[-1] - ts.thrust[-1, 0]) < 0.05 * qp.mass * qp.g


def test_a_series_saved_without_rpy_cmd_loads_with_it_unknown(flight, tmp_path):  # noqa: F811
    from zenswarm.judge.metrics import TimeSeries

    _, sim = flight
    old = {f: getattr(sim.series, f) for f in TimeSeries.FIELDS if f != "rpy_cmd"}
    np.savez_compressed(tmp_path / "old.npz", **old)
    ts = TimeSeries.load(str(tmp_path / "old.npz"))
    assert ts.rpy_cmd.shape == ts.rpy.shape and np.isnan(ts.rpy_cmd).all()
    sim.series.save(str(tmp_path / "new.npz"))
    np.testing.assert_array_equal(TimeSeries.load(str(tmp_path / "new.npz")).rpy_cmd, sim.series.rpy_cmd)
