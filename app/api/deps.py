"""Request dependencies: database session, settings, the authenticated client."""

from __future__ import annotations

import base64
import binascii
from typing import Annotated

from fastapi import Depends, Request
from sqlalchemy.orm import Session

from app.problems import Problem
from core.config import Settings, get_settings
from core.db import get_session
from core.models import Client
from core.security import client_for_key

SessionDep = Annotated[Session, Depends(get_session)]
SettingsDep = Annotated[Settings, Depends(get_settings)]

_BASIC_CHALLENGE = {"WWW-Authenticate": 'Basic realm="vehicle-pose admin", charset="UTF-8"'}


def _presented_key(request: Request) -> str | None:
    """The API key from ``Authorization: Bearer <key>``, or on the admin pages (a browser's
    login) from Basic auth, the password being the key. The API takes Bearer keys only: a
    client that sends its key as Basic auth is told so, not let in."""
    header = request.headers.get("authorization", "")
    scheme, _, value = header.partition(" ")
    if scheme.lower() == "bearer" and value.strip():
        return value.strip()
    if scheme.lower() == "basic" and value.strip() and request.url.path.startswith("/admin"):
        try:
            _, _, password = base64.b64decode(value.strip(), validate=True).decode().partition(":")
        except (binascii.Error, UnicodeDecodeError):
            return None
        return password or None
    return None


def _authenticated(request: Request, session: Session) -> Client | None:
    key = _presented_key(request)
    return client_for_key(session, key) if key else None


def current_client(request: Request, session: SessionDep) -> Client:
    """The client whose key came with the request; 401 otherwise."""
    client = _authenticated(request, session)
    if client is None:
        raise Problem(
            401,
            "unauthorized",
            "send an API key as 'Authorization: Bearer <key>'",
            headers={"WWW-Authenticate": "Bearer"},
        )
    return client


def admin_client(request: Request, session: SessionDep) -> Client:
    """An admin client (API key or Basic auth from a browser); 401 without a key, 403 for a client key."""
    client = _authenticated(request, session)
    if client is None:
        raise Problem(401, "unauthorized", "admin credentials required", headers=_BASIC_CHALLENGE)
    if not client.is_admin:
        raise Problem(403, "forbidden", "this key is not an admin key")
    return client


CurrentClient = Annotated[Client, Depends(current_client)]
AdminClient = Annotated[Client, Depends(admin_client)]
