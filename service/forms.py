"""Turning a submission's form fields and file into validated generation parameters and input facts."""

from __future__ import annotations

import dataclasses
import difflib
import math
import re
import sys
import typing
import unicodedata
from collections.abc import Mapping

from fastapi import Request, params
from fastapi.routing import APIRoute
from starlette.datastructures import FormData

from fastmesh.shapes.shape import EXPORT_FORMATS

from .errors import ApiError


def generation_defaults() -> dict:
    """The pipeline's own defaults (shown in the OpenAPI description and used for omitted fields)."""
    from fastmesh.params import GenerateParams

    return dataclasses.asdict(GenerateParams())


# The spellings a form field of each type accepts: what a person writes, and nothing a lax parser also takes
# ("1_000", "+4", " 5 ", "4.0" for an integer, "yes" / "on" / "" for a flag, subnormal floats).
INT_RE = re.compile(r"-?[0-9]+")
FLOAT_RE = re.compile(r"-?([0-9]+(\.[0-9]*)?|\.[0-9]+)([eE][-+]?[0-9]+)?")
BOOL_WORDS = ("true", "false", "1", "0")


def _plain_type(hint) -> type | None:
    """``int`` for ``int | None`` and the like; None for anything but int, float and bool."""
    args = [a for a in typing.get_args(hint) if a is not type(None)] if typing.get_origin(hint) else [hint]
    return args[0] if len(args) == 1 and args[0] in (int, float, bool) else None


def check_spelling(raw: Mapping[str, object]) -> None:
    """Refuse generation fields sent empty or spelt laxly, per the type :class:`fastmesh.params.GenerateParams`
    declares (a field of another type, a string choice, is left to its own validation).

    Raises
    ------
    ApiError
        422 ``invalid_parameter`` naming the field.
    """
    from fastmesh.params import GenerateParams

    for name, hint in typing.get_type_hints(GenerateParams).items():
        value, kind = raw.get(name), _plain_type(hint)
        if value == "":  # a field sent empty is no value: leaving it out is how a client asks for the default
            raise ApiError(422, "invalid_parameter", f"{name}: empty; leave the field out for its default")
        if not isinstance(value, str) or kind is None:
            continue
        if kind is bool:
            ok, what = value.lower() in BOOL_WORDS, "true or false"
        elif kind is int:
            ok, what = INT_RE.fullmatch(value) is not None, "a whole number written with digits only"
        else:
            ok = FLOAT_RE.fullmatch(value) is not None and (float(value) == 0 or
                                                              abs(float(value)) >= sys.float_info.min)
            what = "a plain decimal number (no subnormal values)"
        if not ok:
            raise ApiError(422, "invalid_parameter", f"{name}: '{value[:30]}' is not {what}")


def declared_fields(route: APIRoute) -> dict[str, bool]:
    """The form and file fields a route takes, its dependencies' included (by their name on the wire), each
    with whether it may be sent more than once (a list)."""
    out, dependants = {}, [route.dependant]
    while dependants:
        dependant = dependants.pop()
        for field in dependant.body_params:
            if isinstance(field.field_info, params.Form):  # File is a kind of Form
                out[field.alias] = typing.get_origin(field.field_info.annotation) is list
        dependants.extend(dependant.dependencies)
    return out


def check_known(form: FormData, fields: Mapping[str, bool]) -> None:
    """Refuse form fields the route does not take, and single fields sent twice.

    A misspelt field (``target_face``) would otherwise be dropped and its default used without a word.

    Raises
    ------
    ApiError
        422 ``unknown_field`` or ``invalid_parameter``, naming the field.
    """
    for name in dict.fromkeys(form.keys()):
        if name not in fields:
            near = difflib.get_close_matches(name, list(fields), n=1)
            hint = f"did you mean '{near[0]}'? " if near else ""
            raise ApiError(422, "unknown_field", f"{name[:40]}: unknown field; {hint}"
                                                 f"the fields are {', '.join(sorted(fields))}")
        count = len(form.getlist(name))
        if count > 1 and not fields[name]:
            raise ApiError(422, "invalid_parameter", f"{name}: sent {count} times; send it once")


async def strict_form(request: Request) -> None:
    """Dependency of the form routes: :func:`check_known` and :func:`check_spelling` on the form as sent (the
    form is parsed once; this reads Starlette's parsed copy)."""
    form = await request.form()
    check_known(form, declared_fields(request.scope["route"]))
    check_spelling(form)


def build_params(values: dict, formats: str | None, default_formats: list[str], limit: int | None = None) -> dict:
    """Validate the generation parameters with the pipeline's own rules; add the export formats.

    ``limit`` is the largest ``max_vertices`` the workers' model accepts, when known.

    Raises
    ------
    ApiError
        422 ``invalid_parameter`` naming the field.
    """
    from fastmesh.params import GenerateParams

    given = {k: v for k, v in values.items() if v is not None}
    for k, v in given.items():
        if isinstance(v, float) and not math.isfinite(v):
            raise ApiError(422, "invalid_parameter", f"{k}: must be a finite number")
    try:
        gp = GenerateParams(**given)
        gp.validate() if limit is None else gp.validate(limit=limit)
    except (TypeError, ValueError) as e:
        raise ApiError(422, "invalid_parameter", str(e)) from None
    out = dataclasses.asdict(gp)
    out["formats"] = parse_formats(formats, default_formats)
    return out


def parse_formats(formats: str | None, default: list[str]) -> list[str]:
    if formats is None or not formats.strip():
        return list(default)
    out = []
    for f in formats.split(","):
        f = f.strip().lower().lstrip(".")
        if f not in EXPORT_FORMATS:
            raise ApiError(422, "invalid_parameter",
                           f"formats: unknown format '{f[:20]}'; use a comma list of {', '.join(EXPORT_FORMATS)}")
        if f not in out:
            out.append(f)
    return out


def safe_filename(name: str | None) -> str:
    """The upload's base name, without directories or control characters, at most 200 characters."""
    name = (name or "").replace("\\", "/").rsplit("/", 1)[-1]
    name = "".join(c for c in name if unicodedata.category(c)[0] != "C").strip().lstrip(".")
    name = re.sub(r"\s+", " ", name)
    if len(name) > 200:  # keep the extension, which names the format
        stem, dot, ext = name.rpartition(".")
        name = (stem[: 190] + dot + ext[:9]) if dot else name[:200]
    return name or "upload"
