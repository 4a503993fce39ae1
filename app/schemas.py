"""Request and response bodies of the API (pydantic), as published in the OpenAPI document."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field

from vehicle_pose.loss.registry import LOSSES
from vehicle_pose.search.optimize import OPTIMIZERS
from vehicle_pose.geometry.parametrize import PARAMETRIZATIONS

Status = Literal["queued", "running", "succeeded", "failed"]


class RegistrationOptionsIn(BaseModel):
    """Engine options a client may set (the ``options`` form field, JSON); defaults are the engine's."""

    model_config = ConfigDict(extra="forbid")

    loss: str | None = Field(default=None, json_schema_extra={"enum": sorted(LOSSES)})
    optimizer: str | None = Field(default=None, json_schema_extra={"enum": sorted(OPTIMIZERS)})
    parametrization: str | None = Field(default=None, json_schema_extra={"enum": sorted(PARAMETRIZATIONS)})
    side: Literal["auto", "left", "right"] | None = None
    color: bool | None = None
    grabcut: bool | None = None
    resegment: bool | None = None
    coarse_to_fine: bool | None = None
    max_evaluations: int | None = Field(default=None, ge=20, le=5000)
    starts: int | None = Field(default=None, ge=1, le=12, description="without init_camera: start poses screened")
    refine: int | None = Field(default=None, ge=1, le=4, description="without init_camera: poses refined at full size")
    edge_weight: float | None = Field(default=None, ge=0.0, le=10.0,
                                      description="with init_camera: weight of the edge alignment term (0: none)")
    box_weight: float | None = Field(default=None, ge=0.0, le=100.0,
                                     description="with init_camera and bbox: weight of the cost of leaving the box")
    fit_start_to_box: bool | None = Field(default=None,
                                          description="with init_camera and bbox: fit the start's place and size to the box")

    def engine_kwargs(self) -> dict[str, Any]:
        """The options that were set, checked against the engine's names."""
        for name, table in (("loss", LOSSES), ("optimizer", OPTIMIZERS), ("parametrization", PARAMETRIZATIONS)):
            value = getattr(self, name)
            if value is not None and value not in table:
                raise ValueError(f"unknown {name} {value!r}; choose one of {', '.join(sorted(table))}")
        return self.model_dump(exclude_none=True)


class Progress(BaseModel):
    stage: str | None
    evaluations: int
    loss: float | None


class JobError(BaseModel):
    type: str = Field(description="stable error type, e.g. /problems/invalid-pose")
    detail: str


class Links(BaseModel):
    self: str
    photo: str
    overlay: str | None = None


class RegistrationOut(BaseModel):
    """A registration job; ``result`` has the same fields as the command line's result.json."""

    id: str
    status: Status
    model_id: str
    created_at: datetime
    started_at: datetime | None
    finished_at: datetime | None
    attempts: int
    photo: dict[str, Any]
    progress: Progress | None = None
    result: dict[str, Any] | None = None
    error: JobError | None = None
    links: Links


class RegistrationAccepted(BaseModel):
    id: str
    status: Status
    links: Links


class ModelOut(BaseModel):
    id: str
    name: str
    units: str
    up: str
    forward: str
    wheels: dict[str, Any] | None
    estimated: list[str]
    links: dict[str, str]
