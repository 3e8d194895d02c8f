"""Deterministic identifiers: the same seed and name always give the same id."""

from __future__ import annotations

import hashlib
import uuid


def _digest(seed: int, *parts: object) -> bytes:
    return hashlib.sha256("/".join(map(str, (seed, *parts))).encode()).digest()


def token(seed: int, *parts: object) -> str:
    """32 hex digits, like the tokens of the nuScenes tables."""
    return _digest(seed, *parts)[:16].hex()


def uuid_like(seed: int, *parts: object) -> str:
    """A version-3-style UUID string, like AV2 log ids and nuScenes map tokens."""
    return str(uuid.UUID(bytes=_digest(seed, *parts)[:16], version=3))
