"""fednav-sim eval --seeds: every figure's mean and spread over several seed sets by one command."""

from __future__ import annotations

import json

import pytest

from fednav.simulators.__main__ import main


def test_seed_sets_give_each_figures_mean_and_spread(capsys):
    assert main(["eval", "demo_aircraft", "--runs", "1", "--seeds", "3,103", "--json"]) == 0
    out = json.loads(capsys.readouterr().out)
    summary, sets = out["seed_sets"], out["sets"]
    assert summary["seeds"] == [3, 103] and [s["seed"] for s in sets] == [3, 103]
    f = summary["figures"]["pipelines.lc.pos_rms_m"]
    values = [s["pipelines"]["lc"]["pos_rms_m"] for s in sets]
    assert f["values"] == values and f["mean"] == pytest.approx(sum(values) / 2)
    assert f["min"] == min(values) < f["max"] == max(values)  # different seeds, different runs
    assert not any(p.startswith("timing") for p in summary["figures"])
    # the table names every pipeline with mean [min - max]
    assert main(["eval", "demo_aircraft", "--runs", "1", "--seeds", "3,103"]) == 0
    text = capsys.readouterr().out
    assert "seed sets [3, 103]" in text and "lc" in text and " - " in text


@pytest.mark.parametrize(
    "argv", [["--seeds", "3"], ["--seeds", "3,3"], ["--seeds", "3,x"], ["--seed", "1", "--seeds", "2,3"]]
)
def test_seed_sets_refused_when_unclear(argv, capsys):
    with pytest.raises(SystemExit) if argv[0] == "--seeds" else _no_raise():
        rc = main(["eval", "demo_aircraft", "--runs", "1", *argv])
        assert rc == 2


class _no_raise:
    def __enter__(self):
        return self

    def __exit__(self, *exc):
        return False
