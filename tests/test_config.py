"""Service configuration: the shipped example loads; errors name the field."""

from pathlib import Path

import pytest

from fednav.service import config

EXAMPLE = Path(__file__).resolve().parents[1] / "service" / "configs" / "example.toml"


def test_example_config_loads():
    cfg = config.load(EXAMPLE)
    assert [p.kind for p in cfg.pipelines] == ["loosely_coupled", "federated", "tightly_coupled"]
    assert cfg.zenoh.listen == ["tcp/127.0.0.1:7447"] and not cfg.zenoh.multicast_scouting


@pytest.mark.parametrize(
    "data, field",
    [
        ({"output": {"solution_rate_hz": -1}}, "output.solution_rate_hz"),
        ({"pipelines": [{"name": "x", "kind": "federated", "sharing": "magic"}]}, "sharing"),
        ({"intake": {"overload": "maybe"}}, "intake.overload"),
        ({"bogus": 1}, "bogus"),
    ],
)
def test_errors_name_the_field(data, field):
    with pytest.raises(config.ConfigError) as ei:
        config.from_dict(data)
    assert field in str(ei.value)


def test_scenario_table_and_missing_table(tmp_path):
    p = tmp_path / "s.toml"
    p.write_text('name = "x"\n[service]\nvehicles = ["a"]\n')
    assert config.load(p, "service").vehicles == ["a"]
    with pytest.raises(config.ConfigError, match="no \\[nope\\] table"):
        config.load(p, "nope")


def test_service_cli_rejects_a_bad_config_naming_the_field(tmp_path):
    import subprocess
    import sys

    p = tmp_path / "bad.toml"
    p.write_text("[output]\nsolution_rate_hz = 0\n")
    res = subprocess.run(
        [sys.executable, "-m", "fednav.service", "--config", str(p)],
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert res.returncode == 2
    assert "output.solution_rate_hz" in res.stderr


def test_recording_kinds_mark_pipelines_without_tests_or_integrity_plain():
    """The recording's blueprint gets no Faults / Integrity panels for a pipeline that publishes
    neither (they would stay empty)."""
    pipes = [
        config.CentralizedConfig(name="c"),
        config.CentralizedConfig(name="c_tested", fault_handling="per_observation"),
        config.TightlyCoupledConfig(name="tc", integrity=False),
        config.TightlyCoupledConfig(name="tc_mhss"),
        config.LooselyCoupledConfig(name="lc"),
        config.UnderwaterConfig(name="uw"),
        config.UnderwaterConfig(name="uw_c", architecture="centralized", usbl_fault_handling="none"),
        config.UnderwaterConfig(name="uw_c_chi2", architecture="centralized"),
        config.UnderwaterConfig(name="uw_untested", usbl_fault_handling="none"),
    ]
    assert config.recording_kinds(pipes) == {
        "c": "plain",
        "c_tested": "centralized",
        "tc": "plain",
        "tc_mhss": "tightly_coupled",
        "lc": "loosely_coupled",
        "uw": "underwater",
        "uw_c": "underwater:centralized,untested",
        "uw_c_chi2": "underwater:centralized",
        "uw_untested": "underwater:untested",
    }


def test_the_fleet_group_is_what_changes_navigation():
    """Services that would navigate a vehicle differently (another IMU model, initialisation,
    solution rate, intake acceptance rules, pipelines) never split a fleet; capacity, scheduling,
    transport and recording settings do not matter."""
    from fednav.service.config import ServiceConfig

    def group(extra: dict) -> str:
        return ServiceConfig.model_validate({"vehicles": ["*"], **extra}).fleet_group()

    base = group({})
    for same in (
        {"intake": {"max_vehicles": 5}},
        {"intake": {"workers": 2, "vehicle_idle_s": 60}},
        {"rrd_vehicle_interval_s": 1.0},
        {"output": {"health_period_s": 2.0}},
    ):
        assert group(same) == base, same
    for other in (
        {"imu": {"grade": "consumer_mems"}},
        {"output": {"solution_rate_hz": 1.0}},
        {"init": {"min_speed_mps": 3.0}},
        {"intake": {"max_imu_gap_s": 1.0}},
        {"major_interval_s": 0.05},
        {"pipelines": [{"name": "lc", "kind": "loosely_coupled", "innovation_gate_sigma": 4.0}]},
        {"prefix": "other"},
    ):
        assert group(other) != base, other


def test_the_shipped_fleet_member_config_shares_the_fleet():
    """docs/fleet.md's service command: two services started with the role's config must split the
    fleet (a rendezvous member, a client of the router), not each serve every vehicle (the page's
    command had only the Zenoh file, service.json5, which leaves a service static: two of them
    served every vehicle twice)."""
    member = config.load(EXAMPLE.parent / "fleet" / "member.toml")
    assert member.vehicles == ["*"] and member.fleet.sharding == "rendezvous"
    assert member.zenoh.mode == "client" and member.zenoh.listen == []
    assert member.zenoh.connect == ["tcp/127.0.0.1:7447"]
    docs = (EXAMPLE.parents[2] / "docs" / "fleet.md").read_text()
    assert "fednav-service --config service/configs/fleet/member.toml" in docs
