"""Readable validation errors: one line per problem, the field named, the closest valid name
suggested for an unknown field, and no links or pydantic internals."""

from __future__ import annotations

import difflib
import types
import typing

from pydantic import BaseModel, ValidationError


def field_names(model: type[BaseModel]) -> set[str]:
    """Every field name of a model and of the models nested in it (unions and lists included)."""
    seen: set[type] = set()
    names: set[str] = set()

    def visit(tp) -> None:
        if isinstance(tp, type) and issubclass(tp, BaseModel):
            if tp in seen:
                return
            seen.add(tp)
            for name, f in tp.model_fields.items():
                names.add(name)
                visit(f.annotation)
            return
        if isinstance(tp, types.UnionType) or typing.get_origin(tp) is not None:
            for arg in typing.get_args(tp):
                visit(arg)

    visit(model)
    return names


def suggest(name: str, candidates) -> str:
    """' (did you mean 'x'?)' for the closest candidate, or ''."""
    close = difflib.get_close_matches(str(name), sorted(candidates), n=1, cutoff=0.6)
    return f" (did you mean '{close[0]}'?)" if close else ""


def format_errors(err: ValidationError, model: type[BaseModel], heading: str) -> str:
    """``heading`` then one line per error: ``  field.path: message``, with a suggestion for an
    unknown field."""
    known = field_names(model)
    lines = [heading]
    for e in err.errors(include_url=False):
        loc = ".".join(str(p) for p in e["loc"]) or "(top level)"
        msg = e["msg"]
        if e["type"] == "extra_forbidden" and e["loc"]:
            msg = "unknown field" + suggest(e["loc"][-1], known)
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
