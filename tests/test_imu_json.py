"""The JSON IMU sample's fast decoder (msgspec) against the contract (the pydantic ImuSample).

``decode_imu_json`` may refuse anything (the service then validates with the model, for the exact
error and counted reason), but what it accepts the model must accept, with bit-identical values.
Fuzzed: numbers of every kind (ints, huge, tiny, negative zero, NaN/Infinity tokens, 1e400),
wrong types, missing, extra, duplicated and escaped keys, wrong lengths, non-objects, truncation.
"""

import json
import math
import random

import pytest
from pydantic import ValidationError

from fednav.service.messages import (
    MAX_DT_S,
    MAX_RATE_RPS,
    MAX_SPECIFIC_FORCE_MPS2,
    ImuSample,
    decode_imu_json,
)

BASE = {
    "t": 1300000000.005,
    "dt_s": 0.005,
    "dtheta_rad": [1e-5, -2e-5, 3e-6],
    "dvel_mps": [0.001, 0.002, 0.049],
}


def model_or_none(payload: bytes):
    try:
        return ImuSample.model_validate_json(payload)
    except ValidationError:
        return None


def same(fast, model) -> bool:
    def bits(x: float) -> str:
        return float(x).hex()

    return (
        bits(fast.t) == bits(model.t)
        and bits(fast.dt_s) == bits(model.dt_s)
        and list(map(bits, fast.dtheta_rad)) == list(map(bits, model.dtheta_rad))
        and list(map(bits, fast.dvel_mps)) == list(map(bits, model.dvel_mps))
    )


NUMBERS = [
    "0",
    "-0",
    "-0.0",
    "1",
    "1e-400",
    "1e400",
    "-1e400",
    "NaN",
    "Infinity",
    "-Infinity",
    "1.7976931348623157e308",
    "12345678901234567890123",
    "true",
    "null",
    '"1.0"',
    "[]",
    "{}",
    "0.005",
    "1.0000000000000002",
    "5e-324",
    "1E2",
    "01",
    "1.",
    ".5",
    "+1",
    "0x10",
]


def text(d: dict) -> str:
    return json.dumps(d, separators=(",", ":"))


def mutations(rng: random.Random):
    """Payloads near the valid one: each an edit of its text or of its structure."""
    keys = ["t", "dt_s", "dtheta_rad", "dvel_mps"]
    while True:
        d = json.loads(json.dumps(BASE))
        pick = rng.randrange(10)
        if pick == 0:  # a scalar replaced by any number token
            k = rng.choice(["t", "dt_s"])
            yield text(d).replace(f'"{k}":{json.dumps(d[k])}', f'"{k}":{rng.choice(NUMBERS)}')
        elif pick == 1:  # an element of a vector replaced
            k = rng.choice(["dtheta_rad", "dvel_mps"])
            v = [json.dumps(x) for x in d[k]]
            v[rng.randrange(3)] = rng.choice(NUMBERS)
            old = f'"{k}":{json.dumps(d[k], separators=(",", ":"))}'
            yield text(d).replace(old, f'"{k}":[{",".join(v)}]')
        elif pick == 2:  # plausible or implausible magnitudes around the limits
            dt = rng.choice([0.005, 1e-9, MAX_DT_S, MAX_DT_S * (1 + 1e-15), 2.0, 0.0, -0.005])
            d["dt_s"] = dt
            lim = rng.choice([MAX_RATE_RPS, MAX_SPECIFIC_FORCE_MPS2])
            k = "dtheta_rad" if lim == MAX_RATE_RPS else "dvel_mps"
            f = rng.choice([0.5, 1.0, 1.0 - 1e-16, 1.0 + 1e-15, 2.0])
            edge = lim * abs(dt) * f
            d[k] = [edge, 0.0, 0.0] if rng.random() < 0.5 else [edge / math.sqrt(3)] * 3
            yield text(d)
        elif pick == 3:  # a key removed, added, or duplicated
            op = rng.randrange(3)
            if op == 0:
                d.pop(rng.choice(keys))
                yield text(d)
            elif op == 1:
                d[rng.choice(["x", "T", "dt", "sensor_id"])] = 1
                yield text(d)
            else:
                k = rng.choice(keys)
                yield text(d)[:-1] + f',"{k}":{json.dumps(d[k])}' + "}"
        elif pick == 4:  # wrong vector lengths
            k = rng.choice(["dtheta_rad", "dvel_mps"])
            d[k] = d[k][: rng.randrange(3)] if rng.random() < 0.5 else d[k] + [0.0]
            yield text(d)
        elif pick == 5:  # keys written with escapes (still "t", ...), or with other case
            yield text(d).replace('"t"', rng.choice(['"\\u0074"', '"T"', '"t "']))
        elif pick == 6:  # times at and beyond the bounds
            d["t"] = rng.choice([0.0, -0.0, -1e-300, 1e10, 1e10 * (1 + 1e-15), 5e9, 123])
            yield text(d)
        elif pick == 7:  # truncated, or with trailing bytes
            s = text(d)
            yield s[: rng.randrange(len(s))] if rng.random() < 0.5 else s + rng.choice([" ", "x", "{}", "\n"])
        elif pick == 8:  # not an object
            yield rng.choice(["[]", "null", "1", '"t"', "", " ", "[{}]"])
        else:  # random valid samples (the fast path must take these)
            d["t"] = rng.uniform(0.0, 2e9)
            d["dt_s"] = rng.choice([0.005, 0.01, 0.0025, rng.uniform(1e-4, 0.1)])
            d["dtheta_rad"] = [rng.gauss(0.0, 1e-3) for _ in range(3)]
            d["dvel_mps"] = [rng.gauss(0.0, 0.05) for _ in range(3)]
            yield text(d)


def test_fast_decoder_accepts_only_what_the_model_accepts_with_identical_values():
    rng = random.Random(20261128)
    gen = mutations(rng)
    accepted_by_model = fast_too = 0
    for _ in range(6000):
        payload = next(gen).encode()
        fast, model = decode_imu_json(payload), model_or_none(payload)
        if fast is not None:
            assert model is not None, payload
            assert same(fast, model), payload
        if model is not None:
            accepted_by_model += 1
            fast_too += fast is not None
    # the fast path is not a decoder that refuses everything: it takes what the model takes
    assert accepted_by_model > 1000
    assert fast_too == accepted_by_model


@pytest.mark.parametrize(
    "payload",
    [
        b'{"t":NaN,"dt_s":0.005,"dtheta_rad":[0,0,0],"dvel_mps":[0,0,0]}',
        b'{"t":1,"dt_s":0.005,"dtheta_rad":[1e400,0,0],"dvel_mps":[0,0,0]}',
        b'{"t":1,"dt_s":0.005,"dtheta_rad":[true,0,0],"dvel_mps":[0,0,0]}',
        b'{"t":1,"dt_s":0.005,"dtheta_rad":[0,0,0],"dvel_mps":[0,0,0],"x":1}',
        b'{"t":1,"dt_s":0.005,"dtheta_rad":[1,0,0],"dvel_mps":[0,0,0]}',  # 200 rad/s
        b'{"t":1,"dt_s":0,"dtheta_rad":[0,0,0],"dvel_mps":[0,0,0]}',
        b'{"t":"1","dt_s":0.005,"dtheta_rad":[0,0,0],"dvel_mps":[0,0,0]}',
    ],
)
def test_what_the_model_refuses_the_fast_decoder_refuses(payload):
    assert model_or_none(payload) is None
    assert decode_imu_json(payload) is None
