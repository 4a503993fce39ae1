"""Database tables: API clients and registration jobs."""

from __future__ import annotations

import enum
import uuid
from datetime import UTC, datetime
from typing import Any

from sqlalchemy import (
    JSON,
    Boolean,
    ColumnElement,
    DateTime,
    Float,
    ForeignKey,
    Index,
    Integer,
    String,
    Text,
    UniqueConstraint,
    Update,
    update,
)
from sqlalchemy.orm import DeclarativeBase, Mapped, mapped_column, relationship


def utcnow() -> datetime:
    return datetime.now(UTC)


def new_id() -> str:
    return uuid.uuid4().hex


class Base(DeclarativeBase):
    pass


class JobStatus(str, enum.Enum):  # noqa: UP042 (StrEnum would change str(), which the records store)
    queued = "queued"
    running = "running"
    succeeded = "succeeded"
    failed = "failed"


class Client(Base):
    """Whoever holds an API key; admins may read every job, upload models and see /admin."""

    __tablename__ = "clients"

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    name: Mapped[str] = mapped_column(String(100), unique=True)
    key_hash: Mapped[str] = mapped_column(String(64), unique=True)
    is_admin: Mapped[bool] = mapped_column(Boolean, default=False)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)


class Registration(Base):
    """One registration job: its inputs (storage keys and hints), progress and outcome."""

    __tablename__ = "registrations"
    __table_args__ = (
        UniqueConstraint("client_id", "idempotency_key", name="uq_registrations_client_idempotency"),
        Index("ix_registrations_created_at", "created_at"),
        Index("ix_registrations_client_created", "client_id", "created_at"),
        Index("ix_registrations_status", "status"),
        Index("ix_registrations_model_id", "model_id"),
    )

    id: Mapped[str] = mapped_column(String(32), primary_key=True, default=new_id)
    client_id: Mapped[str] = mapped_column(ForeignKey("clients.id"))
    client: Mapped[Client] = relationship(lazy="joined")
    idempotency_key: Mapped[str | None] = mapped_column(String(200), default=None)
    request_hash: Mapped[str | None] = mapped_column(String(64), default=None)
    model_id: Mapped[str] = mapped_column(String(64))
    status: Mapped[str] = mapped_column(String(16), default=JobStatus.queued.value)
    created_at: Mapped[datetime] = mapped_column(DateTime(timezone=True), default=utcnow)
    started_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), default=None)
    finished_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), default=None)
    duration_s: Mapped[float | None] = mapped_column(Float, default=None)

    photo_key: Mapped[str] = mapped_column(String(200))
    photo_media_type: Mapped[str] = mapped_column(String(50))
    photo_width: Mapped[int] = mapped_column(Integer)
    photo_height: Mapped[int] = mapped_column(Integer)
    init_camera: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
    bbox: Mapped[list[float] | None] = mapped_column(JSON, default=None)
    options: Mapped[dict[str, Any]] = mapped_column(JSON, default=dict)

    attempts: Mapped[int] = mapped_column(Integer, default=0)
    worker: Mapped[str | None] = mapped_column(String(200), default=None)
    # Renewed by the process running the job (its lease): a running job whose heartbeat is
    # older than the lease has lost its worker and is sent again (worker.jobs.reap_stale_jobs).
    heartbeat_at: Mapped[datetime | None] = mapped_column(DateTime(timezone=True), default=None)
    stage: Mapped[str | None] = mapped_column(String(50), default=None)
    evaluations: Mapped[int] = mapped_column(Integer, default=0)
    current_loss: Mapped[float | None] = mapped_column(Float, default=None)

    result: Mapped[dict[str, Any] | None] = mapped_column(JSON, default=None)
    loss: Mapped[float | None] = mapped_column(Float, default=None)
    seconds: Mapped[float | None] = mapped_column(Float, default=None)
    overlay_key: Mapped[str | None] = mapped_column(String(200), default=None)
    thumbnail_key: Mapped[str | None] = mapped_column(String(200), default=None)
    error_type: Mapped[str | None] = mapped_column(String(50), default=None)
    error_detail: Mapped[str | None] = mapped_column(Text, default=None)

    @property
    def parts_key(self) -> str | None:
        """Where the part map PNG is kept: written with the overlay by every registration whose
        result lists its parts (:func:`parts_key`)."""
        return parts_key(self.id) if self.overlay_key and self.result and "parts" in self.result else None

    @property
    def ended(self) -> bool:
        """The job succeeded or failed; it will not run again."""
        return self.status in (JobStatus.succeeded.value, JobStatus.failed.value)

    @property
    def never_queued(self) -> bool:
        """The job failed at submission because the queue could not be reached: it never ran."""
        return self.status == JobStatus.failed.value and self.error_type == "broker-unavailable" and self.attempts == 0

    def requeue_submission(self) -> None:
        """Make a never-queued job queued again (a client's retry with the same Idempotency-Key)."""
        self.status = JobStatus.queued.value
        self.finished_at = None
        self.duration_s = None
        self.error_type = None
        self.error_detail = None

    def finish(self, status: JobStatus, error_type: str | None = None, detail: str | None = None) -> None:
        """End the job: its final status, the time to result, and the reason when it failed."""
        self.status = status.value
        self.finished_at = utcnow()
        self.duration_s = max(0.0, (self.finished_at - as_utc(self.created_at)).total_seconds())
        if status is JobStatus.failed:
            self.error_type = error_type or "internal-error"
            self.error_detail = detail or ""


def parts_key(job_id: str) -> str:
    """The storage key of a registration's part map PNG."""
    return f"parts/{job_id}.png"


def requeued(*where: ColumnElement[bool]) -> Update:
    """The UPDATE that puts the running jobs matching ``where`` back to ``queued`` (stage
    ``retrying``): a job whose run was cut off and that will run again says so."""
    return (update(Registration)
            .where(Registration.status == JobStatus.running.value, *where)
            .values(status=JobStatus.queued.value, stage="retrying"))


def as_utc(t: datetime) -> datetime:
    """SQLite returns naive datetimes for timezone-aware columns; they are UTC."""
    return t if t.tzinfo is not None else t.replace(tzinfo=UTC)
