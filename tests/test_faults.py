"""Fault injection: each kind gives its specified signal inside its window and nothing outside."""

from __future__ import annotations

import math

import numpy as np
import pytest
from pydantic import ValidationError

from fednav.service.messages import ActiveFault
from fednav.simulators.faults import FaultSet, parse_faults

CH = ["pos_e", "pos_n", "pos_u"]
ZERO = {"pos_e": 0.0, "pos_n": 0.0, "pos_u": 0.0, "vel_e": 0.0}


def _fs(**kw) -> FaultSet:
    base = dict(sensor="gnss", start_s=10.0, duration_s=5.0, channels=CH)
    base.update(kw)
    return FaultSet([base], np.random.default_rng(42))


def test_step_window_is_half_open_and_other_channels_untouched():
    fs = _fs(kind="step", magnitude=[1.0, -2.0, 3.5])
    for t, on in [(9.999, False), (10.0, True), (12.0, True), (14.999, True), (15.0, False), (100.0, False)]:
        out = fs.apply("gnss", t, dict(ZERO, vel_e=7.0))
        assert out == (
            {"pos_e": 1.0, "pos_n": -2.0, "pos_u": 3.5, "vel_e": 7.0} if on else dict(ZERO, vel_e=7.0)
        )
    # other sensors are untouched
    assert fs.apply("star", 12.0, {"pos_e": 1.0}) == {"pos_e": 1.0}


def test_ramp_grows_linearly_from_onset():
    fs = _fs(kind="ramp", rate_per_s=[1.0, 0.5, -2.0])
    out = fs.apply("gnss", 13.0, ZERO)
    assert out["pos_e"] == pytest.approx(3.0, abs=1e-12)
    assert out["pos_n"] == pytest.approx(1.5, abs=1e-12)
    assert out["pos_u"] == pytest.approx(-6.0, abs=1e-12)
    assert fs.apply("gnss", 15.0, ZERO) == ZERO


def test_oscillation_follows_the_sine():
    fs = _fs(
        kind="oscillation", amplitude=[2.0, 1.0, 0.5], freq_hz=[0.1, 1.0, 0.0], phase_rad=[0.0, 0.5, 1.0]
    )
    for t in (10.0, 10.3, 11.7, 14.9):
        out = fs.apply("gnss", t, ZERO)
        tau = t - 10.0
        assert out["pos_e"] == pytest.approx(2.0 * math.sin(2 * math.pi * 0.1 * tau), abs=1e-12)
        assert out["pos_n"] == pytest.approx(1.0 * math.sin(2 * math.pi * 1.0 * tau + 0.5), abs=1e-12)
        assert out["pos_u"] == pytest.approx(0.5 * math.sin(1.0), abs=1e-12)


def test_scale_multiplies_the_value_passed():
    fs = _fs(kind="scale", factor=[2.0, 0.0, -1.0])
    assert fs.apply("gnss", 11.0, {"pos_e": 3.0, "pos_n": 5.0, "pos_u": 7.0}) == {
        "pos_e": 6.0,
        "pos_n": 0.0,
        "pos_u": -7.0,
    }
    assert fs.apply("gnss", 16.0, {"pos_e": 3.0, "pos_n": 5.0, "pos_u": 7.0}) == {
        "pos_e": 3.0,
        "pos_n": 5.0,
        "pos_u": 7.0,
    }


def test_faults_compose_in_list_order():
    fs = FaultSet(
        parse_faults(
            [
                dict(
                    sensor="gnss",
                    kind="step",
                    start_s=0.0,
                    duration_s=10.0,
                    channels=["pos_e"],
                    magnitude=[1.0],
                ),
                dict(
                    sensor="gnss",
                    kind="scale",
                    start_s=0.0,
                    duration_s=10.0,
                    channels=["pos_e"],
                    factor=[3.0],
                ),
            ]
        ),
        np.random.default_rng(0),
    )
    assert fs.apply("gnss", 1.0, {"pos_e": 1.0})["pos_e"] == 6.0  # (1 + 1) * 3


def test_noise_has_the_stated_mean_and_std():
    fs = _fs(kind="noise", duration_s=1e6, mean=[1.0, 0.0, -5.0], std=[2.0, 0.5, 0.0])
    x = np.array([[v for v in fs.apply("gnss", 10.0 + 0.01 * i, ZERO).values()][:3] for i in range(20_000)])
    # 20000 samples: mean error 0.7 % of std, std error 0.5 %; tolerances 3 %
    assert np.all(np.abs(x.mean(axis=0) - [1.0, 0.0, -5.0]) <= [0.06, 0.015, 1e-12])
    np.testing.assert_allclose(x.std(axis=0), [2.0, 0.5, 0.0], rtol=0.03, atol=1e-12)
    assert abs(np.corrcoef(x[1:, 0], x[:-1, 0])[0, 1]) < 0.03  # white


def test_random_walk_variance_grows_linearly():
    n_ch = 3000
    chans = [f"C{i:02d}.pseudorange" for i in range(n_ch)]
    fs = FaultSet(
        [
            dict(
                sensor="gnss_raw",
                kind="random_walk",
                start_s=10.0,
                duration_s=100.0,
                channels=chans,
                sigma_per_sqrt_s=[0.5] * n_ch,
            )
        ],
        np.random.default_rng(3),
    )
    zero = dict.fromkeys(chans, 0.0)
    w = {}
    for t in (11.0, 14.0, 19.0, 19.5):
        w[t] = np.array(list(fs.apply("gnss_raw", t, zero).values()))
    # var = sigma^2 (t - start): 0.25, 1.0, 2.25 (3000 channels: 2.6 % std error; 8 % tolerance)
    for t, tau in ((11.0, 1.0), (14.0, 4.0), (19.0, 9.0)):
        assert w[t].var() == pytest.approx(0.25 * tau, rel=0.08)
    # increments are independent of the past and have variance sigma^2 dt
    inc = w[19.5] - w[19.0]
    assert inc.var() == pytest.approx(0.25 * 0.5, rel=0.08)
    assert abs(np.corrcoef(inc, w[19.0])[0, 1]) < 0.06
    with pytest.raises(ValueError, match="backwards"):
        fs.apply("gnss_raw", 15.0, zero)


def test_random_draws_are_seeded_and_per_fault():
    specs = [
        dict(
            sensor="gnss",
            kind="noise",
            start_s=0.0,
            duration_s=100.0,
            channels=["pos_e"],
            mean=[0.0],
            std=[1.0],
        ),
        dict(
            sensor="star",
            kind="random_walk",
            start_s=0.0,
            duration_s=100.0,
            channels=["roll"],
            sigma_per_sqrt_s=[1.0],
        ),
    ]
    a, b = FaultSet(specs, np.random.default_rng(5)), FaultSet(specs, np.random.default_rng(5))
    # b interleaves calls to the other fault: the gnss noise sequence must not change
    seq_a = [a.apply("gnss", float(t), {"pos_e": 0.0})["pos_e"] for t in range(10)]
    seq_b = []
    for t in range(10):
        b.apply("star", float(t), {"roll": 0.0})
        seq_b.append(b.apply("gnss", float(t), {"pos_e": 0.0})["pos_e"])
    assert seq_a == seq_b
    c = FaultSet(specs, np.random.default_rng(6))
    assert seq_a != [c.apply("gnss", float(t), {"pos_e": 0.0})["pos_e"] for t in range(10)]


def test_active_lists_the_faults_in_their_windows():
    fs = FaultSet(
        parse_faults(
            [
                dict(
                    sensor="gnss",
                    kind="step",
                    start_s=300.0,
                    duration_s=10.0,
                    channels=["vel_e"],
                    magnitude=[2.5],
                ),
                dict(
                    sensor="star",
                    kind="ramp",
                    start_s=305.0,
                    duration_s=1.0,
                    channels=["yaw"],
                    rate_per_s=[1.0],
                ),
            ]
        ),
        np.random.default_rng(0),
    )
    assert fs.active(299.99) == []
    assert fs.active(300.0) == [ActiveFault(sensor="gnss", kind="step", channels=["vel_e"])]
    assert [f.sensor for f in fs.active(305.5)] == ["gnss", "star"]
    assert fs.active(310.0) == []


def test_missing_channel_is_an_error():
    fs = _fs(kind="step", magnitude=[1.0, 2.0, 3.0])
    with pytest.raises(KeyError, match="pos_u"):
        fs.apply("gnss", 11.0, {"pos_e": 0.0, "pos_n": 0.0})


@pytest.mark.parametrize(
    "spec, message",
    [
        (dict(kind="step", magnitude=[1.0]), r"magnitude has 1 values but channels has 3"),
        (
            dict(kind="oscillation", amplitude=[1.0] * 3, freq_hz=[1.0] * 3),
            r"oscillation\.phase_rad\n  Field required",
        ),
        (
            dict(kind="noise", mean=[0.0] * 3, std=[1.0, -1.0, 1.0]),
            r"noise\.std\.1\n  Input should be greater",
        ),
        (dict(kind="drift", magnitude=[1.0] * 3), r"does not match any of the expected tags"),
        (
            dict(kind="step", magnitude=[1.0] * 3, duration_s=0.0),
            r"step\.duration_s\n  Input should be greater",
        ),
        (dict(kind="step", magnitude=[1.0] * 3, factor=[2.0] * 3), r"step\.factor\n  Extra inputs"),
        (dict(kind="scale", factor=[1.0] * 3, channels=["a", "a", "b"]), r"channels has duplicates"),
    ],
)
def test_invalid_specs_name_the_field(spec, message):
    base = dict(sensor="gnss", start_s=1.0, duration_s=2.0, channels=CH)
    base.update(spec)
    with pytest.raises(ValidationError, match=message):
        parse_faults([base])
