"""Readable validation errors: one line per problem, the field named, the closest valid name
suggested for an unknown field, and no links or pydantic internals."""

from __future__ import annotations

import difflib
import types
import typing

from pydantic import BaseModel, ValidationError


def _members(tp) -> list:
    """The types an annotation admits: unions, ``X | None`` and ``Annotated`` opened."""
    origin = typing.get_origin(tp)
    if origin is typing.Annotated:
        return _members(typing.get_args(tp)[0])
    if isinstance(tp, types.UnionType) or origin is typing.Union:
        return [m for a in typing.get_args(tp) for m in _members(a)]
    return [tp]


def _is_model(tp) -> bool:
    return isinstance(tp, type) and issubclass(tp, BaseModel)


def _is_tag(model: type[BaseModel], item) -> bool:
    """Whether an error location's ``item`` names this member of a union: its discriminator's
    value (a ``Literal`` field) or, for a union without one, its class name."""
    if item == model.__name__:
        return True
    return any(
        typing.get_origin(f.annotation) is typing.Literal and item in typing.get_args(f.annotation)
        for f in model.model_fields.values()
    )


def field_names(model: type[BaseModel], path=()) -> set[str]:
    """The field names valid at ``path`` (an error location, field names, list indexes, dict keys
    and union tags) inside ``model``: those of the model(s) there, not of the models nested in them.
    Empty where the path leads to no model (a suggestion from elsewhere would mislead)."""
    here = _members(model)
    for item in path:
        step = []
        for tp in here:
            args = typing.get_args(tp)
            origin = typing.get_origin(tp)
            if _is_model(tp):
                if isinstance(item, str) and item in tp.model_fields:
                    step += _members(tp.model_fields[item].annotation)
            elif origin in (list, set, frozenset) and args and isinstance(item, int):
                step += _members(args[0])
            elif origin is dict and len(args) == 2:
                step += _members(args[1])
        # no field, item or value: pydantic's tag of a union's member (discriminator value or class name)
        here = step or [tp for tp in here if _is_model(tp) and _is_tag(tp, item)]
    return {name for tp in here if _is_model(tp) for name in tp.model_fields}


def suggest(name: str, candidates) -> str:
    """' (did you mean 'x'?)' for the closest candidate, or ''."""
    close = difflib.get_close_matches(str(name), sorted(candidates), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


def format_errors(err: ValidationError, model: type[BaseModel], heading: str) -> str:
    """``heading`` then one line per error: ``  field.path: message``, with a suggestion for an
    unknown field (from the fields of the model at its location)."""
    lines = [heading]
    for e in err.errors(include_url=False):
        loc = ".".join(str(p) for p in e["loc"]) or "(top level)"
        msg = e["msg"]
        if e["type"] == "extra_forbidden" and e["loc"]:
            *path, name = e["loc"]
            msg = "unknown field" + suggest(name, field_names(model, path) - {name})
        elif e["type"] == "union_tag_invalid":
            ctx = e.get("ctx", {})
            known = [t.strip(" '") for t in str(ctx.get("expected_tags", "")).split(",")]
            tag = ctx.get("tag")
            msg = f"unknown kind {tag!r}{suggest(tag, known)}; known: {', '.join(known)}"
        elif e["type"] == "literal_error":
            msg = f"{msg}; got {e.get('input')!r}"
        lines.append(f"  {loc}: {msg}")
    return "\n".join(lines)


_RANGE_ERRORS = {"greater_than", "greater_than_equal", "less_than", "less_than_equal"}


#: (reason, the error types that give it), first match wins
_REASONS = (
    ("malformed_json", {"json_invalid", "json_type"}),
    ("non_finite", {"finite_number"}),
    ("absurd_value", {"value_error"}),
    ("out_of_range", _RANGE_ERRORS),
)


def classify(err) -> str:
    """Rejection reason of a pydantic validation error, as Health counts it (the service's worker
    and the ROS 2 bridge both use it)."""
    types = {e["type"] for e in err.errors()}
    return next((reason for reason, ts in _REASONS if types & ts), "schema")


def reason_and_text(err) -> tuple[str, str]:
    """:func:`classify`'s reason and the message of the error that gave it, with its field (a log
    line naming one reason with another error's text, 'non_finite: ... Extra inputs are not
    permitted', misleads)."""
    reason = classify(err)
    errors = err.errors(include_url=False)
    ts = dict(_REASONS).get(reason)
    e = next((e for e in errors if ts is None or e["type"] in ts), errors[0])
    loc = ".".join(str(p) for p in e["loc"])
    return reason, f"{loc}: {e['msg']}" if loc else e["msg"]
