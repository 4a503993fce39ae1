"""Request and response bodies of the API (pydantic), as published in the OpenAPI document."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import BaseModel, ConfigDict, Field, create_model

from vehicle_pose.registration.options import RegistrationOptions

Status = Literal["queued", "running", "succeeded", "failed"]


class _OptionsBase(BaseModel):
    model_config = ConfigDict(extra="forbid")

    def engine_kwargs(self) -> dict[str, Any]:
        """The options that were set, by name, checked by the engine's own validation
        (ValueError naming the field and the reason)."""
        values = self.model_dump(exclude_none=True)
        RegistrationOptions.from_flat(values)
        return values


def _options_model() -> type[_OptionsBase]:
    """The engine's public options (registration/options.py), each optional, with the
    engine's bounds, choices and help: a new public option appears here by itself."""
    fields: dict[str, Any] = {}
    for name, f, spec in RegistrationOptions.specs():
        if not spec.public:
            continue
        kind: Any = type(f.default)
        if spec.choices is not None:
            kind = Literal.__getitem__(spec.choices)
            bounds: dict[str, Any] = {}
        elif kind is tuple:
            kind, bounds = list[float], {"max_length": 8}
        else:
            bounds = {"ge": spec.low, "le": spec.high}
        fields[name] = (kind | None, Field(default=None, description=spec.help, **bounds))
    model: type[_OptionsBase] = create_model(
        "RegistrationOptionsIn", __base__=_OptionsBase,
        __doc__="Engine options a client may set (the ``options`` form field, JSON); defaults are the engine's.",
        **fields)
    return model


RegistrationOptionsIn = _options_model()


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
    parts: str | None = None


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
