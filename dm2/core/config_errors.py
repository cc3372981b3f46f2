"""Configuration errors a user can act on: the bad value shown, the nearest known key named.

:func:`describe_errors` turns a pydantic ``ValidationError`` into one line per error, naming
the file, the field (``monitor.voxel_mm``), the problem and the value given (``got -1``); an
unknown key gets the nearest known key of its table (``did you mean 'voxel_mm'?``).
"""

from __future__ import annotations

import difflib
import typing

from pydantic import BaseModel, ValidationError


def describe_errors(source: str, exc: ValidationError, model=None) -> str:
    lines = []
    for err in exc.errors():
        loc = ".".join(str(p) for p in err["loc"]) or "(top level)"
        msg = err["msg"].removeprefix("Value error, ")
        if err["type"] == "extra_forbidden":
            msg = "unknown key"
            known = known_keys(model, err["loc"][:-1])
            near = difflib.get_close_matches(str(err["loc"][-1]), known, n=1, cutoff=0.6)
            if near:
                msg += f" (did you mean '{near[0]}'?)"
        elif "input" in err and not isinstance(err["input"], dict):
            msg += f" (got {_shown(err['input'])})"
        lines.append(f"{source}: field '{loc}': {msg}")
    return "\n".join(lines)


def _shown(value, limit: int = 80) -> str:
    text = repr(value)
    return text if len(text) <= limit else text[:limit - 3] + "..."


def model_named(base: type, title: str):
    """The subclass of ``base`` (or ``base`` itself) a ValidationError's title names."""
    stack = [base]
    while stack:
        cls = stack.pop()
        if cls.__name__ == title:
            return cls
        stack.extend(cls.__subclasses__())
    return None


def known_keys(model, loc) -> list[str]:
    """Field names (aliases where given) of the table at ``loc`` below ``model``."""
    cls = model
    for part in loc:
        if cls is None:
            return []
        if isinstance(part, int):
            continue
        fields = getattr(cls, "model_fields", {})
        field = fields.get(part) or next((f for f in fields.values() if f.alias == part), None)
        if field is None:
            return []
        cls = _inner_model(field.annotation)
    if cls is None or not hasattr(cls, "model_fields"):
        return []
    return [f.alias or name for name, f in cls.model_fields.items()]


def _inner_model(annotation):
    if isinstance(annotation, type) and issubclass(annotation, BaseModel):
        return annotation
    for arg in typing.get_args(annotation):
        found = _inner_model(arg)
        if found is not None:
            return found
    return None
