"""/v1/models: the model library; admins upload meshes."""

from __future__ import annotations

import logging
import shutil
import tempfile
from pathlib import Path
from typing import Annotated, Any, Literal

from fastapi import APIRouter, File, Form, UploadFile, status
from fastapi.responses import JSONResponse

from app.api.deps import AdminClient, CurrentClient, SettingsDep
from app.problems import Problem
from app.schemas import ModelOut
from core.library import get_library, get_store
from vehicle_pose import EmptyMeshError, ModelError, UnknownModelError
from vehicle_pose.model.library import MODEL_ID, install_model
from vehicle_pose.model.metadata import UNITS, ModelInfo

log = logging.getLogger(__name__)
router = APIRouter(prefix="/v1/models", tags=["models"])

_PROBLEM: dict[str, Any] = {"content": {"application/problem+json": {}}}
MESH_SUFFIXES = (".glb", ".gltf", ".obj", ".ply", ".off", ".stl")
Axis = Literal["+x", "-x", "+y", "-y", "+z", "-z"]


def _out(info: ModelInfo) -> ModelOut:
    return ModelOut(
        id=info.id,
        name=info.name,
        units=info.units,
        up=info.up,
        forward=info.forward,
        wheels=info.wheels.to_dict() if info.wheels is not None else None,
        estimated=list(info.estimated),
        links={"self": f"/v1/models/{info.id}"},
    )


def _prepare_soon(model_id: str) -> None:
    """Ask a worker to prepare the new model's levels now rather than at its first job."""
    from core.queue import PREPARE_TASK, get_breaker, get_celery

    try:
        get_breaker().send(get_celery(), PREPARE_TASK, args=[model_id])
    except Exception as exc:  # kombu raises many connection error types; the model works regardless
        log.warning("cannot ask a worker to prepare model %s: %s", model_id, exc)


@router.get("", response_model=list[ModelOut])
def list_models(_: CurrentClient) -> list[ModelOut]:
    """Every model a registration may name."""
    library = get_library()
    return [_out(library.info(model_id)) for model_id in library.ids()]


@router.get("/{model_id}", response_model=ModelOut, responses={404: _PROBLEM})
def get_model(model_id: str, _: CurrentClient) -> ModelOut:
    """One model's metadata (wheel geometry, axes, which fields were estimated)."""
    try:
        return _out(get_library().info(model_id))
    except UnknownModelError as exc:
        raise Problem(404, "not-found", str(exc)) from None


@router.post(
    "",
    status_code=status.HTTP_201_CREATED,
    response_model=ModelOut,
    responses={code: _PROBLEM for code in (401, 403, 409, 413, 415, 422)},
)
def upload_model(
    _: AdminClient,
    settings: SettingsDep,
    mesh: Annotated[UploadFile, File(description="mesh file: GLB, GLTF (embedded), OBJ, PLY, OFF or STL")],
    model_id: Annotated[str, Form(pattern=MODEL_ID.pattern)],
    name: Annotated[str | None, Form(max_length=100)] = None,
    up: Annotated[Axis, Form()] = "+z",
    forward: Annotated[Axis, Form()] = "+x",
    units: Annotated[str, Form(description=f"one of {', '.join(UNITS)}")] = "m",
) -> JSONResponse:
    """Add a model (admin); wheel metadata is estimated from the mesh and marked as estimated."""
    suffix = Path(mesh.filename or "").suffix.lower()
    if suffix not in MESH_SUFFIXES:
        raise Problem(415, "unsupported-media-type", f"mesh file name must end in one of {', '.join(MESH_SUFFIXES)}")
    library = get_library()
    if model_id in library:
        raise Problem(409, "model-exists", f"model {model_id!r} exists already")
    assert settings.upload_models_dir is not None
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / f"upload{suffix}"
        with path.open("wb") as f:
            shutil.copyfileobj(mesh.file, f)
        try:
            info = install_model(settings.upload_models_dir, model_id, path, name=name, up=up, forward=forward,
                                 units=units, store=get_store())
        except EmptyMeshError as exc:
            raise Problem(422, "empty-mesh", str(exc)) from None
        except ModelError as exc:
            raise Problem(422, "invalid-model", str(exc)) from None
    _prepare_soon(model_id)
    body = _out(info).model_dump(mode="json")
    return JSONResponse(body, status_code=201, headers={"Location": f"/v1/models/{model_id}"})
