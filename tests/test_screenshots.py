"""make screenshots: every blueprint panel has data in a real recording, and (when a system
Chromium and Playwright are present) Rerun's web viewer renders a tab in headless Chromium."""

from __future__ import annotations

import importlib.util

import pytest
import rerun.blueprint as rrb

from fednav.dashboards import screenshots as shots
from fednav.dashboards.blueprints import build_blueprint
from fednav.dashboards.record import record
from fednav.simulators.evaluate import service_config
from fednav.simulators.scenario import load_scenario


def test_panel_filters_match_like_rerun():
    assert shots._match("/v1/fed/isolation/**", "/v1/fed/isolation/INS_BDS")
    assert shots._match("/v1/fed/isolation/**", "/v1/fed/isolation")
    assert not shots._match("/v1/fed/isolation/**", "/v1/fed/isolation_x")
    assert shots._match("/v1/lc/error/east_m", "/v1/lc/error/east_m")
    assert not shots._match("/v1/lc/error/east_m", "/v1/lc/error/east_m/x")
    assert not shots._match("- /v1/**", "/v1/a")


def test_empty_panels_names_the_views_without_data():
    bp = build_blueprint("v1", {"lc": "loosely_coupled"})
    empty = shots.empty_panels(bp, ["/v1/lc/error/east_m"])
    names = {(p.tab, p.name) for p in empty}
    assert ("Overview", "position error east (m), all pipelines") not in names
    assert ("Health", "queue depth") in names
    assert all(isinstance(p.filters, list) and p.filters for p in empty)


def test_panels_follow_each_pipelines_features():
    """Underwater: no sharing panel for a centralised filter, no reconfiguration log without a
    test; transfer alignment: one sub-tab per node (ids from the kind) with the node's errors."""
    from fednav.dashboards.blueprints import family_of, features_of

    assert family_of("underwater:centralized,untested") == "underwater"
    assert features_of("transfer_alignment:wing1,wing2") == ("wing1", "wing2")
    bp = build_blueprint(
        "v1",
        {
            "uw": "underwater",
            "uw_c": "underwater:centralized,untested",
            "uw_c2": "underwater:centralized",
            "ta": "transfer_alignment:wing1,wing2",
        },
    )
    names = {p.name for _, node in shots.tabs_of(bp) for p in shots._views(node, "")}
    assert {"uw: sharing coefficients", "uw: reconfiguration, injected faults (truth)"} <= names
    assert "uw_c2: reconfiguration, injected faults (truth)" in names
    assert not any(n.startswith(("uw_c: sharing", "uw_c2: sharing", "uw_c: reconfiguration")) for n in names)
    assert "uw_c: DVL offset (m/s) and 1σ" in names
    panels = {p.name: p.filters for _, node in shots.tabs_of(bp) for p in shots._views(node, "")}
    assert "/v1/uw/states/dvl_offset_x_mps/**" in panels["uw: DVL offset (m/s) and 1σ"]
    mis = panels["wing2: misalignment error ±3σ (arcmin)"]
    assert "/v1/ta/alignment_error/wing2.misalignment_x_p3s" in mis and len(mis) == 9
    assert not any("wing1" in f for f in mis)


@pytest.fixture(scope="module")
def demo_rrd(tmp_path_factory):
    sc = load_scenario("demo_product")
    path = tmp_path_factory.mktemp("shots") / "demo.rrd"
    record(sc, path, optimize=True, duration_s=45.0)
    return sc, path


def test_every_panel_of_the_demo_has_data(demo_rrd):
    sc, path = demo_rrd
    cfg = service_config(sc)
    bp = build_blueprint("v1", {p.name: p.kind for p in cfg.pipelines})
    ents = shots.recorded_entities(path)
    assert len(ents) > 100
    empty = shots.empty_panels(bp, ents)
    assert not empty, [(p.tab, p.name, p.filters) for p in empty]
    tabs = [n for n, _ in shots.tabs_of(bp)]
    assert tabs[:3] == ["Overview", "Trajectory", "Errors"]
    assert {"Integrity", "Faults & sharing", "Health"} <= set(tabs)


def test_web_viewer_renders_a_tab_in_headless_chromium(demo_rrd, tmp_path):
    chromium = shots.find_chromium()
    if chromium is None:
        pytest.skip("no system chromium (apt-get install -y chromium) for the headless web viewer")
    if importlib.util.find_spec("playwright") is None:
        pytest.skip("playwright not installed (the 'screenshots' extra of pyproject.toml)")
    sc, path = demo_rrd
    cfg = service_config(sc)
    pipelines = {p.name: p.kind for p in cfg.pipelines}

    def bp(_i):
        from fednav.dashboards.blueprints import vehicle_tabs

        tabs = vehicle_tabs("v1", pipelines)
        return rrb.Blueprint(
            rrb.Tabs(*tabs.contents, active_tab=0, name="v1"),
            rrb.BlueprintPanel(state="collapsed"),
            rrb.SelectionPanel(state="collapsed"),
            auto_views=False,
        )

    saved = shots.capture(path, bp, ["Overview"], tmp_path, "demo", chromium, load_timeout_s=180.0)
    assert len(saved) == 1 and saved[0].is_file()
    data = saved[0].read_bytes()
    assert data[:8] == b"\x89PNG\r\n\x1a\n"
    # an empty or still-loading viewer is grey and white (0.3 % coloured pixels measured, with
    # the side panels open); the rendered overview's lines, lanes and legends are about 1 %
    assert shots.coloured_fraction(saved[0]) > shots.BLANK_FRACTION
