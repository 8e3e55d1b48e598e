"""fednav-sim eval progress bar: drawn on a terminal, silent otherwise (and with --json)."""

import io

from fednav.simulators.progress import EvalProgress
from fednav.simulators.scenario import load_scenario


def test_bar_counts_scenario_seconds_of_all_runs():
    sc = load_scenario("demo_product")
    out = io.StringIO()
    bar = EvalProgress(sc, 2, enabled=True, file=out)
    t0 = float(sc.t0_gps_s)
    for t in range(0, 121, 10):
        bar.at(0, t0 + t)
    assert bar._bar.n == 120
    bar.run_done(1, 2, 1.0)
    bar.at(1, t0 + 60.0)
    assert bar._bar.n == 180
    assert "run 2/2" in bar._bar.desc
    bar.run_done(2, 2, 2.0)
    assert bar._bar.n == 240
    bar.close()
    text = out.getvalue()
    assert "scenario s" in text and "demo_product run" in text


def test_disabled_bar_is_silent():
    bar = EvalProgress(load_scenario("demo_product"), 3, enabled=False)
    bar.at(0, 1.0)
    bar.run_done(1, 3, 0.1)
    bar.close()
    assert bar._bar is None


def test_eval_json_prints_no_progress(capsys, monkeypatch):
    """--json (or a pipe) keeps stderr empty: the bar is off, no per-run lines either."""
    from fednav.simulators import __main__ as cli

    monkeypatch.setattr("sys.stderr.isatty", lambda: True, raising=False)
    import fednav.simulators.evaluate as ev

    monkeypatch.setattr(ev, "evaluate", lambda *a, **k: {"ok": 1})
    assert cli.main(["eval", "demo_product", "--json"]) == 0
    cap = capsys.readouterr()
    assert cap.err == "" and '"ok": 1' in cap.out
