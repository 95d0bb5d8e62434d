"""The submission form of ``POST /v1/jobs`` and ``POST /v1/batches``, as dependencies.

The generation fields are made from :data:`fastmesh.params.PARAMETERS` (:func:`generation_field`), the
others are declared here, and both routes take the whole form as one dependency: :data:`JobForm` (one
``file``) or :data:`BatchForm` (``files``, repeated).  The form's parts are dependencies of their own,
declared in the order ``Idempotency-Key``, upload, fields: FastAPI validates the dependencies in that order,
so a request with several faults has them named in that order, the order of the schema.
"""

from __future__ import annotations

import inspect
from dataclasses import dataclass
from typing import Annotated, Literal

from fastapi import Depends, File, Form, Header, UploadFile

from fastmesh.params import PARAMETERS, Parameter
from fastmesh_jobs.settings import Settings


def formats_description(default_formats: list[str]) -> str:
    """The ``formats`` field's description for an app that exports ``default_formats`` when a job names none
    (the schema states the app's own; :func:`service.routes.jobs.document_settings`)."""
    return f"Comma list of glb, obj, ply exported with the job (default {','.join(default_formats)})."


def generation_field(prm: Parameter):
    """The form field of one generation parameter: its type (a choice as a ``Literal``), None meaning the
    default, its ``BOUNDS`` range as ``ge`` / ``le`` (so the OpenAPI schema states it), its help."""
    kind = Literal[prm.choices] if prm.choices else prm.type
    checks = prm.bound.form_range() if prm.bound else {}
    if prm.type is float:
        checks["allow_inf_nan"] = False
    example = prm.example if prm.example is not None or prm.type is bool else prm.default
    described = prm.described(f"default {prm.default!r}")
    return Annotated[kind | None, Form(description=described[0].upper() + described[1:] + ".",
                                       examples=None if example is None else [example], **checks)]


# The description names the default formats of an app with default settings; each app's schema states its own.
Formats = Annotated[str | None, Form(description=formats_description(
    Settings.model_fields["default_formats"].get_default(call_default_factory=True)), examples=["glb,obj"])]
CallbackUrl = Annotated[str | None, Form(max_length=2000,
                                         description="https URL POSTed the job JSON, signed, when it succeeds, "
                                                     "fails or is cancelled (README, Webhooks).",
                                         examples=["https://example.com/fastmesh-hook"])]


@dataclass(frozen=True)
class FormFields:
    """The form's fields: generation parameters as sent (None = the default), export formats, webhook URL."""

    generation: dict
    formats: str | None
    callback_url: str | None


async def form_fields(**values) -> FormFields:
    """The form's fields, as one dependency: its signature (:func:`form_signature`) declares them to FastAPI."""
    # async: nothing here waits, so FastAPI runs it on the event loop rather than in a worker thread
    formats, callback_url = values.pop("formats", None), values.pop("callback_url", None)
    return FormFields(values, formats, callback_url)


def form_signature() -> inspect.Signature:
    """The fields of :func:`form_fields`: the generation parameters in the order of ``GenerateParams``
    (:func:`generation_field`), then ``formats`` and ``callback_url``; each may be left out (None)."""
    fields = [(prm.name, generation_field(prm)) for prm in PARAMETERS]
    fields += [("formats", Formats), ("callback_url", CallbackUrl)]
    return inspect.Signature([inspect.Parameter(name, inspect.Parameter.KEYWORD_ONLY, default=None, annotation=hint)
                              for name, hint in fields], return_annotation=FormFields)


form_fields.__signature__ = form_signature()


async def idempotency_key(key: Annotated[str | None, Header(alias="Idempotency-Key", max_length=200,
                                                            description="Retrying with the same key returns "
                                                                        "the same job.")] = None) -> str | None:
    return key


async def upload(file: Annotated[UploadFile, File(description="Mesh or point cloud; the extension names the "
                                                              "format.")]) -> UploadFile:
    return file


async def uploads(files: Annotated[list[UploadFile], File(description="The shapes: repeat the field once per "
                                                                      "file.")]) -> list[UploadFile]:
    return files


@dataclass(frozen=True)
class Submission:
    """A submission's form: its ``Idempotency-Key``, upload(s) and fields."""

    idempotency_key: str | None
    files: list[UploadFile]
    fields: FormFields


async def job_form(key: Annotated[str | None, Depends(idempotency_key)],
                   file: Annotated[UploadFile, Depends(upload)],
                   form: Annotated[FormFields, Depends(form_fields)]) -> Submission:
    return Submission(key, [file], form)


async def batch_form(key: Annotated[str | None, Depends(idempotency_key)],
                     files: Annotated[list[UploadFile], Depends(uploads)],
                     form: Annotated[FormFields, Depends(form_fields)]) -> Submission:
    return Submission(key, files, form)


JobForm = Annotated[Submission, Depends(job_form)]
BatchForm = Annotated[Submission, Depends(batch_form)]
