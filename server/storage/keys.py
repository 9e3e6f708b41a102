"""Repository of API keys: create (plaintext shown once), verify, revoke. Never commits.

A key is ``mlk_`` followed by 43 URL-safe characters (32 random bytes from ``secrets``).
Only its sha256 hex digest is stored: the key is a high-entropy random token, not a
human password, so a slow password hash (scrypt, argon2) would add latency to every
request without adding security; a stolen database does not reveal usable keys.

Verification looks the key up by its first 12 characters (the non-secret ``prefix``,
also shown in listings) and compares the sha256 digests with ``hmac.compare_digest``,
so neither the database lookup nor the comparison depends on the secret part.
Scopes: ``localize`` (vehicles), ``map:write`` (uploads, entries), ``metrics`` (a
Prometheus scraper: ``/metrics`` only), ``admin`` (maps, keys);
``ApiKeyRecord.has_scope`` treats ``admin`` as granting every scope.
"""

from __future__ import annotations

import hashlib
import hmac
import secrets
from collections.abc import Iterable

from sqlalchemy import select
from sqlalchemy.orm import Session

from monoloc.core.errors import ConflictError, InvalidInputError, NotFoundError
from monoloc.server.storage.models import ApiKey, Map, utc_now
from monoloc.server.storage.records import ApiKeyRecord

SCOPES = ("localize", "map:write", "metrics", "admin")
KEY_PREFIX = "mlk_"
PREFIX_CHARS = 12  # "mlk_" + 8 random characters: enough to tell keys apart in a listing
_TOKEN_BYTES = 32


def hash_api_key(plaintext: str) -> str:
    """sha256 hex digest of an API key."""
    return hashlib.sha256(plaintext.encode("utf-8")).hexdigest()


def parse_scopes(scopes: Iterable[str] | str) -> frozenset[str]:
    """Scopes from a list or a comma-separated string; InvalidInputError on unknown ones."""
    items = scopes.split(",") if isinstance(scopes, str) else list(scopes)
    clean = frozenset(s.strip() for s in items if s.strip())
    unknown = sorted(clean - set(SCOPES))
    if unknown:
        raise InvalidInputError(f"unknown scope(s) {unknown}; valid scopes: {', '.join(SCOPES)}")
    if not clean:
        raise InvalidInputError(f"an API key needs at least one scope of {', '.join(SCOPES)}")
    return clean


def _record(row: ApiKey) -> ApiKeyRecord:
    return ApiKeyRecord(
        id=row.id,
        name=row.name,
        prefix=row.prefix,
        scopes=frozenset(s for s in row.scopes.split(",") if s),
        created_at=row.created_at,
        revoked_at=row.revoked_at,
        maps=None if row.maps is None else frozenset(int(m) for m in row.maps),
    )


def _check_maps(session: Session, maps: Iterable[int], scopes: frozenset[str]) -> list[int]:
    wanted = sorted({int(m) for m in maps})
    if not wanted:
        raise InvalidInputError("maps: give at least one map id, or leave maps out for all maps")
    if "admin" in scopes:
        raise InvalidInputError("maps: an admin key sees every map; limit only other keys")
    found = set(session.scalars(select(Map.id).where(Map.id.in_(wanted))))
    missing = [m for m in wanted if m not in found]
    if missing:
        raise InvalidInputError(f"maps: map(s) {missing} do not exist")
    return wanted


def create_api_key(
    session: Session,
    name: str,
    scopes: Iterable[str] | str,
    maps: Iterable[int] | None = None,
) -> tuple[ApiKeyRecord, str]:
    """Create a key, limited to ``maps`` (existing map ids) if given; returns (record,
    plaintext). The plaintext is not stored anywhere: show it to the user once."""
    name = str(name).strip()
    if not 1 <= len(name) <= 128:
        raise InvalidInputError(f"API key name must be 1-128 characters, got {name!r}")
    clean = parse_scopes(scopes)
    map_ids = None if maps is None else _check_maps(session, maps, clean)
    plaintext = KEY_PREFIX + secrets.token_urlsafe(_TOKEN_BYTES)
    row = ApiKey(
        name=name,
        prefix=plaintext[:PREFIX_CHARS],
        key_hash=hash_api_key(plaintext),
        scopes=",".join(sorted(clean)),
        maps=map_ids,
    )
    session.add(row)
    session.flush()
    return _record(row), plaintext


def verify_api_key(session: Session, plaintext: str | None) -> ApiKeyRecord | None:
    """The active key matching ``plaintext``, or None (unknown, malformed or revoked)."""
    if not plaintext or not plaintext.startswith(KEY_PREFIX) or len(plaintext) > 256:
        return None
    digest = hash_api_key(plaintext)
    candidates = session.scalars(
        select(ApiKey).where(ApiKey.prefix == plaintext[:PREFIX_CHARS])
    ).all()
    match = None
    for row in candidates:  # compare all candidates: timing does not reveal which matched
        if hmac.compare_digest(row.key_hash.encode(), digest.encode()):
            match = row
    if match is None or match.revoked_at is not None:
        return None
    return _record(match)


def _is_admin(row: ApiKey) -> bool:
    return "admin" in row.scopes.split(",")


def revoke_api_key(session: Session, key_id: int) -> ApiKeyRecord:
    """Revoke a key (idempotent: revoking twice keeps the first revocation time).
    ConflictError if it is the last active admin key."""
    row = session.get(ApiKey, key_id)
    if row is None:
        raise NotFoundError(f"API key {key_id} does not exist")
    if row.revoked_at is None and _is_admin(row):
        # Lock every active key (PostgreSQL): two revocations of the last two admin
        # keys run one after the other, the second sees the first's.
        active = session.scalars(
            select(ApiKey).where(ApiKey.revoked_at.is_(None), ApiKey.id != key_id).with_for_update()
        )
        if not any(_is_admin(other) for other in active):
            raise ConflictError(
                f"API key {key_id} is the last active admin key: create another admin key "
                "before revoking it (no one could manage the server's keys and maps)"
            )
    if row.revoked_at is None:
        row.revoked_at = utc_now()
        session.flush()
    return _record(row)


def list_api_keys(session: Session, *, include_revoked: bool = True) -> list[ApiKeyRecord]:
    stmt = select(ApiKey).order_by(ApiKey.id)
    if not include_revoked:
        stmt = stmt.where(ApiKey.revoked_at.is_(None))
    return [_record(r) for r in session.scalars(stmt)]
