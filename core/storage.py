"""Where photos and overlays live: a local folder by default, an S3-compatible bucket at scale.

Jobs carry storage keys (``photos/<id>``), never image bytes.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager
from functools import lru_cache
from pathlib import Path
from typing import Protocol

from core.config import Settings, get_settings
from vehicle_pose.files import write_atomic


class ObjectMissing(KeyError):
    """No object is stored under this key."""


class StorageUnavailable(OSError):
    """The store could not be reached (connection refused, reset, timed out): a transient
    failure, retried like the other OSErrors of a job."""


class Storage(Protocol):
    def put(self, key: str, data: bytes, content_type: str) -> None: ...

    def get(self, key: str) -> bytes: ...

    def delete(self, key: str) -> None: ...

    def ping(self) -> None: ...


def _check_key(key: str) -> str:
    parts = key.split("/")
    if not key or key.startswith("/") or any(p in ("", ".", "..") for p in parts):
        raise ValueError(f"invalid storage key {key!r}")
    return key


class LocalStorage:
    """Objects as files under ``root``; each write is atomic (temporary file, then rename)."""

    def __init__(self, root: str | Path) -> None:
        self.root = Path(root)

    def _path(self, key: str) -> Path:
        return self.root / _check_key(key)

    def put(self, key: str, data: bytes, content_type: str) -> None:
        write_atomic(self._path(key), data)

    def get(self, key: str) -> bytes:
        try:
            return self._path(key).read_bytes()
        except FileNotFoundError:
            raise ObjectMissing(key) from None

    def delete(self, key: str) -> None:
        self._path(key).unlink(missing_ok=True)

    def ping(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        if not os.access(self.root, os.W_OK):
            raise OSError(f"storage folder {self.root} is not writable")


class S3Storage:
    """Objects in an S3-compatible bucket (AWS S3, MinIO); needs the ``s3`` extra (boto3)."""

    def __init__(self, bucket: str, prefix: str, settings: Settings) -> None:
        import boto3  # optional dependency: only deployments with S3 storage install it

        self.bucket = bucket
        self.prefix = prefix.strip("/")
        self._client = boto3.client(
            "s3",
            endpoint_url=settings.s3_endpoint_url,
            region_name=settings.s3_region,
            aws_access_key_id=settings.s3_access_key.get_secret_value() if settings.s3_access_key else None,
            aws_secret_access_key=settings.s3_secret_key.get_secret_value() if settings.s3_secret_key else None,
        )

    def _key(self, key: str) -> str:
        return f"{self.prefix}/{_check_key(key)}" if self.prefix else _check_key(key)

    @contextmanager
    def _reachable(self) -> Iterator[None]:
        from botocore.exceptions import ConnectionError as BotoConnectionError
        from botocore.exceptions import HTTPClientError

        try:
            yield
        except (BotoConnectionError, HTTPClientError) as exc:
            raise StorageUnavailable(f"the object store cannot be reached: {exc}") from None

    def put(self, key: str, data: bytes, content_type: str) -> None:
        with self._reachable():
            self._client.put_object(Bucket=self.bucket, Key=self._key(key), Body=data, ContentType=content_type)

    def get(self, key: str) -> bytes:
        with self._reachable():
            try:
                body: bytes = self._client.get_object(Bucket=self.bucket, Key=self._key(key))["Body"].read()
                return body
            except self._client.exceptions.NoSuchKey:
                raise ObjectMissing(key) from None

    def delete(self, key: str) -> None:
        with self._reachable():
            self._client.delete_object(Bucket=self.bucket, Key=self._key(key))

    def ping(self) -> None:
        with self._reachable():
            self._client.head_bucket(Bucket=self.bucket)


def make_storage(settings: Settings) -> Storage:
    """The storage named by ``settings.storage_url``: ``s3://bucket/prefix`` or a folder path."""
    url = settings.storage_url
    if url.startswith("s3://"):
        bucket, _, prefix = url[5:].partition("/")
        return S3Storage(bucket, prefix, settings)
    return LocalStorage(url.removeprefix("file://"))


@lru_cache
def get_storage() -> Storage:
    """The process's storage."""
    return make_storage(get_settings())
