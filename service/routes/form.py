"""The submission form of ``POST /v1/jobs`` and ``POST /v1/batches``, as dependencies.

Each field is declared once here, as an ``Annotated`` alias, and both routes take the whole form as one
dependency: :data:`JobForm` (one ``file``) or :data:`BatchForm` (``files``, repeated).  The form's parts are
dependencies of their own, declared in the order ``Idempotency-Key``, upload, fields: FastAPI validates the
dependencies in that order, so a request with several faults has them named in that order, the order of the
schema.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Annotated, Literal

from fastapi import Depends, File, Form, Header, UploadFile

from fastmesh.params import BOUNDS
from fastmesh_jobs.settings import Settings

from ..forms import generation_defaults

DEFAULTS = generation_defaults()


def _default(name: str) -> str:
    return f"default {DEFAULTS.get(name)!r}"


def formats_description(default_formats: list[str]) -> str:
    """The ``formats`` field's description for an app that exports ``default_formats`` when a job names none
    (the schema states the app's own; :func:`service.routes.jobs.document_settings`)."""
    return f"Comma list of glb, obj, ply exported with the job (default {','.join(default_formats)})."


Seed = Annotated[int | None, Form(**BOUNDS["seed"].form_range(), description=f"Sampling seed ({_default('seed')}).",
                                  examples=[0])]
Temperature = Annotated[float | None, Form(allow_inf_nan=False,
                                           description=f"Sampling temperature ({_default('temperature')}).",
                                           examples=[DEFAULTS.get("temperature")])]
TopK = Annotated[int | None, Form(**BOUNDS["top_k"].form_range(),
                                  description=f"Top-k sampling, 0 = off ({_default('top_k')}).",
                                  examples=[DEFAULTS.get("top_k")])]
TopP = Annotated[float | None, Form(allow_inf_nan=False, description=f"Nucleus sampling ({_default('top_p')}).",
                                    examples=[DEFAULTS.get("top_p")])]
MaxVertices = Annotated[int | None, Form(**BOUNDS["max_vertices"].form_range(),
                                         description="Vertex budget; unset = the model's limit "
                                                     f"({_default('max_vertices')}).",
                                         examples=[DEFAULTS.get("max_vertices")])]
Enhancer = Annotated[bool | None, Form(description=f"Run the vertex enhancer ({_default('enhancer')}).")]
Filtering = Annotated[bool | None, Form(description="Prediction filtering, masked re-predictions of the edges "
                                                    f"({_default('filtering')}).")]
Candidates = Annotated[int | None, Form(**BOUNDS["candidates"].form_range(),
                                        description="Meshes sampled (seeds seed, seed+1, ...); the one nearest the "
                                                    f"input is returned; 1 is fastest ({_default('candidates')}).",
                                        examples=[DEFAULTS.get("candidates")])]
TargetFaces = Annotated[int | None, Form(**BOUNDS["target_faces"].form_range(),
                                         description="Faces to aim for, held within 20 % (result.quality gives "
                                                     "target_faces, faces and target_met); unset = the model "
                                                     "chooses the count from the shape.", examples=[300])]
Closed = Annotated[Literal["auto", "true", "false"] | None, Form(
    description="Close the result's holes: auto = when the input is closed (a closed mesh, or oriented points "
                "that enclose a volume); the decision is in result.quality "
                f"({_default('closed')}).", examples=["auto"])]
Topology = Annotated[Literal["triangle", "quad"] | None, Form(
    description="quad: pairs of triangles that make a near-planar, well-shaped quad become one, in the OBJ and "
                "PLY files (GLB holds triangles); result.quality.quad_share says how many "
                f"({_default('topology')}).", examples=["quad"])]
Uv = Annotated[bool | None, Form(description="Give the result a UV layout (xatlas), in the GLB (TEXCOORD_0) and "
                                             f"OBJ (vt) files ({_default('uv')}).")]
Bake = Annotated[bool | None, Form(description="With uv: bake a textured glTF input's base colour onto the "
                                               f"layout, into the GLB's texture ({_default('bake')}).")]
Origin = Annotated[Literal["input", "center", "bottom"] | None, Form(
    description="Where the result's origin lies: the input's own frame, its bounding box's centre or its bottom "
                f"centre (Y up) ({_default('origin')}).", examples=["bottom"])]
Height = Annotated[float | None, Form(allow_inf_nan=False, **BOUNDS["height"].form_range(),
                                      description="Scale the result to stand this many metres tall along Y "
                                                  "(unset: the input's size).", examples=[1.8])]
Up = Annotated[Literal["y", "z"] | None, Form(description="Up axis of the OBJ and PLY files; GLB is always Y-up, "
                                                          f"as glTF requires ({_default('up')}).", examples=["z"])]
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


async def form_fields(seed: Seed = None, temperature: Temperature = None, top_k: TopK = None, top_p: TopP = None,
                 max_vertices: MaxVertices = None, enhancer: Enhancer = None, filtering: Filtering = None,
                 candidates: Candidates = None, target_faces: TargetFaces = None, closed: Closed = None,
                 topology: Topology = None, uv: Uv = None, bake: Bake = None, origin: Origin = None,
                 height: Height = None, up: Up = None, formats: Formats = None,
                 callback_url: CallbackUrl = None) -> FormFields:
    # async: nothing here waits, so FastAPI runs it on the event loop rather than in a worker thread
    generation = {"seed": seed, "temperature": temperature, "top_k": top_k, "top_p": top_p,
                  "max_vertices": max_vertices, "enhancer": enhancer, "filtering": filtering,
                  "candidates": candidates, "target_faces": target_faces, "closed": closed, "topology": topology,
                  "uv": uv, "bake": bake, "origin": origin, "height": height, "up": up}
    return FormFields(generation, formats, callback_url)


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
