"""API keys: random tokens shown once, stored as SHA-256 digests."""

from __future__ import annotations

import hashlib
import secrets

from sqlalchemy import select
from sqlalchemy.orm import Session

from core.models import Client

KEY_PREFIX = "vp_"


def new_key() -> str:
    """A fresh API key (256 random bits)."""
    return KEY_PREFIX + secrets.token_urlsafe(32)


def hash_key(key: str) -> str:
    """The stored form of a key; keys are random, so a plain digest cannot be brute-forced."""
    return hashlib.sha256(key.encode()).hexdigest()


def create_client(session: Session, name: str, *, admin: bool = False, key: str | None = None) -> str:
    """Add a client and return its API key (the only time the key is seen)."""
    key = key or new_key()
    session.add(Client(name=name, key_hash=hash_key(key), is_admin=admin))
    session.flush()
    return key


def client_for_key(session: Session, key: str) -> Client | None:
    """The client holding ``key``, if any."""
    return session.scalars(select(Client).where(Client.key_hash == hash_key(key))).first()
