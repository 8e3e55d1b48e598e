"""``fednav-fleet record`` through a failover: a problem seen only in the snapshots taken while a
killed service's heir takes its vehicles over (~0.1-1 s) is transient, not an exit 1; one that
lasts is (docs/fleet.md, "record")."""

from __future__ import annotations

import threading

from fednav.dashboards import fleet as fleet_cli


class _Sub:
    def undeclare(self) -> None:
        pass


class _Session:
    def declare_subscriber(self, key, cb):
        return _Sub()


class _Fleet:
    """Snapshots of a fleet of two vehicles: ``bad[k]`` the problems of snapshot k."""

    prefix = "fednav"

    def __init__(self, bad: list[list[str]]):
        self.session = _Session()
        self.bad = bad
        self.k = 0

    def snapshot(self) -> dict:
        problems = self.bad[min(self.k, len(self.bad) - 1)]
        self.k += 1
        vehicles = [
            {"vehicle": v, "served_twice": False, "services": ["a" * 32], "pipelines": {}, "by_service": {}}
            for v in ("veh0", "veh1")
        ]
        return {"vehicles": vehicles, "services": [], "problems": problems}


def test_a_problem_of_one_snapshot_is_transient_and_one_that_lasts_is_not(tmp_path):
    gap = "vehicle veh1 is published (its publisher announces it) but no service serves it"
    stuck = "vehicle veh0 is served by 2 services: a, b"
    # 20 snapshots at 10 Hz: veh1 unserved in one snapshot (a failover), veh0 served twice for 1.5 s
    # at first, then again from snapshot 15 to the end (still there when the recording stops)
    bad = [[stuck] if k < 15 else [] for k in range(20)]
    bad[8] = [gap]
    bad[15:] = [[stuck]] * 5
    res = fleet_cli.record(_Fleet(bad), tmp_path / "f.rrd", 1.95, 10.0, threading.Event())
    assert res["transient"] == [gap], res
    assert res["problems"] == [stuck], res  # 1.4 s at first, but still there at the end

    bad = [[]] * 10
    bad[3] = [gap]
    res = fleet_cli.record(_Fleet(bad), tmp_path / "g.rrd", 0.95, 10.0, threading.Event())
    assert res["problems"] == [] and res["transient"] == [gap], res

    bad = [[gap]] * 40  # 4 s: a vehicle nobody takes over
    res = fleet_cli.record(_Fleet(bad + [[]]), tmp_path / "h.rrd", 4.05, 10.0, threading.Event())
    assert res["problems"] == [gap] and res["transient"] == [], res
