"""Wire models: strictness, plausibility limits, committed JSON Schemas match the models."""

import json
from pathlib import Path

import pytest
from pydantic import ValidationError

from fednav.service import keys
from fednav.service.app import classify
from fednav.service.messages import ImuSample, all_messages, json_schemas

SCHEMAS = Path(__file__).resolve().parents[1] / "docs" / "schemas"


def test_committed_schemas_match_models():
    expected = json_schemas()
    on_disk = {
        p.name.removesuffix(".schema.json"): json.loads(p.read_text()) for p in SCHEMAS.glob("*.schema.json")
    }
    assert set(on_disk) == {m.__name__ for m in all_messages()}, "run `make schemas` and commit docs/schemas"
    for name, schema in expected.items():
        assert on_disk[name] == json.loads(json.dumps(schema)), f"{name} schema drifted: run `make schemas`"


def _imu(**kw):
    d = {"t": 100.0, "dt_s": 0.01, "dtheta_rad": [0.0, 0.0, 1e-4], "dvel_mps": [0.0, 0.0, 0.098]}
    d.update(kw)
    return json.dumps(d)


@pytest.mark.parametrize(
    "payload, reason",
    [
        ("{not json", "malformed_json"),
        (_imu(extra=1), "schema"),
        (_imu(dt_s="0.01"), "schema"),
        (_imu(dtheta_rad=[0.0, 0.0]), "schema"),
        (_imu(dvel_mps=[float("nan"), 0.0, 0.0]), "non_finite"),
        (_imu(dvel_mps=[1e9, 0.0, 0.0]), "absurd_value"),
        (_imu(dt_s=-0.01), "out_of_range"),
    ],
)
def test_bad_imu_rejected_with_reason(payload, reason):
    with pytest.raises(ValidationError) as ei:
        ImuSample.model_validate_json(payload)
    assert classify(ei.value) == reason


def test_good_imu_round_trip():
    m = ImuSample.model_validate_json(_imu())
    assert ImuSample.model_validate_json(m.to_json()) == m
    assert ImuSample.encoding() == "application/json;fednav.ImuSample/1"


def test_keys_round_trip():
    k = keys.sensor("v1", "gnss_fix", "main")
    assert k == "fednav/v1/sensor/gnss/main/fix"
    p = keys.parse_input(k)
    assert (p.vehicle, p.kind, p.sensor_id) == ("v1", "gnss_fix", "main")
    assert keys.parse_input("fednav/v1/sensor/imu/wing1").kind == "imu"
    assert keys.parse_input("fednav/v1/truth").kind == "truth"
    assert keys.parse_input("fednav/v1/sensor/bogus/x") is None
    assert keys.parse_input("other/v1/truth") is None
    with pytest.raises(ValueError):
        keys.sensor("v/1", "imu", "main")


def test_schemas_are_2020_12_with_uri_ids_and_every_field_described():
    from urllib.parse import urlparse

    from jsonschema import Draft202012Validator

    from fednav.service.messages import json_schemas

    for name, schema in json_schemas().items():
        assert schema["$schema"] == "https://json-schema.org/draft/2020-12/schema"
        assert urlparse(schema["$id"]).scheme == "urn" and name in schema["$id"]
        Draft202012Validator.check_schema(schema)
        parts = [(name, schema)] + [(f"{name}/$defs/{d}", s) for d, s in schema.get("$defs", {}).items()]
        undescribed = [
            f"{where}.{p}"
            for where, s in parts
            for p, ps in s.get("properties", {}).items()
            if not ps.get("description")
        ]
        assert not undescribed, undescribed


def test_a_refusal_names_the_error_that_gave_its_reason():
    """A message with two problems (an extra field, a NaN): the reason is non_finite and its text
    the NaN's, with the field ('non_finite: ... Extra inputs are not permitted' misled)."""
    from fednav.service.validation_errors import reason_and_text

    raw = b'{"t": 1.0, "dt_s": 0.01, "dtheta_rad": [NaN, 0, 0], "dvel_mps": [0, 0, 9.8], "junk": 1}'
    with pytest.raises(ValidationError) as ei:
        ImuSample.model_validate_json(raw)
    reason, text = reason_and_text(ei.value)
    assert reason == "non_finite" and text.startswith("dtheta_rad.0: ") and "finite" in text, text
