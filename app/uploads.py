"""Upload safety: a body size limit enforced while the bytes stream in, a deadline for the body
to arrive, and content sniffing."""

from __future__ import annotations

import asyncio
from collections.abc import Callable

from starlette.exceptions import HTTPException
from starlette.requests import Request
from starlette.types import ASGIApp, Message, Receive, Scope, Send

from app.problems import problem_response

# Magic numbers of the photo formats the engine decodes (HEIF and AVIF below); the declared
# Content-Type is ignored.
_SIGNATURES: tuple[tuple[bytes, int, str], ...] = (
    (b"\xff\xd8\xff", 0, "image/jpeg"),
    (b"\x89PNG\r\n\x1a\n", 0, "image/png"),
    (b"WEBP", 8, "image/webp"),
    (b"II*\x00", 0, "image/tiff"),
    (b"MM\x00*", 0, "image/tiff"),
    (b"BM", 0, "image/bmp"),
)


# HEIF and AVIF are ISO base media files: a "ftyp" box first, whose brands (the major one at
# bytes 8-12, compatible ones from byte 16 to the box's end) say what the file holds.
_HEIC_BRANDS = frozenset((b"heic", b"heix", b"heim", b"heis", b"hevc", b"hevx", b"hevm", b"hevs"))
_HEIF_BRANDS = frozenset((b"mif1", b"msf1", b"mif2"))
_AVIF_BRANDS = frozenset((b"avif", b"avis"))

SNIFF_BYTES = 64
"""How many of a file's first bytes :func:`sniff_image` needs to tell every format apart."""


def _iso_media_type(head: bytes) -> str | None:
    """The media type of a HEIF or AVIF file from its ``ftyp`` box, or None when it is neither."""
    if head[4:8] != b"ftyp" or len(head) < 12:
        return None
    size = int.from_bytes(head[0:4], "big")
    brands = [head[8:12]] + [head[i : i + 4] for i in range(16, min(size, len(head)) - 3, 4)]
    for kinds, media_type in ((_AVIF_BRANDS, "image/avif"), (_HEIC_BRANDS, "image/heic"),
                              (_HEIF_BRANDS, "image/heif")):
        if any(b in kinds for b in brands):
            return media_type
    return None


def sniff_image(head: bytes) -> str | None:
    """The media type of an image from its first bytes (:data:`SNIFF_BYTES` of them tell every
    format), or None when it is no supported image."""
    for magic, offset, media_type in _SIGNATURES:
        if head[offset : offset + len(magic)] == magic:
            if media_type == "image/webp" and not head.startswith(b"RIFF"):
                continue
            return media_type
    return _iso_media_type(head)


class BodySizeLimit:
    """Refuse request bodies over a limit with 413, before or while they are received, and
    bodies that do not arrive in time with 408.

    A declared ``Content-Length`` over the limit is refused before reading anything; a body
    without one (chunked) is counted as it arrives and refused once it passes the limit, so no
    more than the limit is ever read or written to disk. A body must have arrived whole within
    ``timeout_s`` of the request's start: a client that sends half a body and stops (or sends a
    byte now and then) is answered 408 and its connection closed, instead of holding a
    connection and an upload's buffers open without end.
    """

    def __init__(self, app: ASGIApp, limit_for: Callable[[str], int | None], timeout_s: float = 60.0) -> None:
        self.app = app
        self.limit_for = limit_for
        self.timeout_s = timeout_s

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http" or scope["method"] not in ("POST", "PUT", "PATCH"):
            await self.app(scope, receive, send)
            return
        limit = self.limit_for(scope["path"])
        if limit is None:
            await self.app(scope, receive, send)
            return
        declared = dict(scope["headers"]).get(b"content-length")
        if declared is not None and declared.isdigit() and int(declared) > limit:
            await _too_large(scope, receive, send, limit)
            return
        received = 0
        whole = False
        loop = asyncio.get_running_loop()
        deadline = loop.time() + self.timeout_s

        async def limited_receive() -> Message:
            nonlocal received, whole
            if whole:
                return await receive()
            try:
                message = await asyncio.wait_for(receive(), timeout=max(deadline - loop.time(), 0.0))
            except TimeoutError:
                # An HTTPException passes through FastAPI's body parsing unchanged (it wraps others as 400).
                raise HTTPException(408, f"the request body did not arrive within {self.timeout_s:g} s",
                                    headers={"Connection": "close"}) from None
            if message["type"] == "http.request":
                received += len(message.get("body", b""))
                whole = not message.get("more_body", False)
                if received > limit:
                    raise HTTPException(413, f"the request body exceeds {limit} bytes")
            return message

        await self.app(scope, limited_receive, send)


async def _too_large(scope: Scope, receive: Receive, send: Send, limit: int) -> None:
    response = problem_response(
        Request(scope), 413, "content-too-large", f"the request body exceeds {limit} bytes", {"Connection": "close"}
    )
    await response(scope, receive, send)
