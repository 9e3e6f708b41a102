"""Start-up chores: the bootstrap admin key and leftovers of interrupted uploads.

Bootstrap: with ``MONOLOC_BOOTSTRAP_ADMIN_KEY`` set and no API key in the database, that
key is stored (hashed) as an admin key named ``bootstrap``. Once any key exists the
setting is ignored, so it cannot resurrect a revoked key; rotate by creating a new admin
key and revoking ``bootstrap``. The value must look like a generated key (``mlk_`` and
at least 32 URL-safe characters): a short human password would be a weak admin key.
"""

from __future__ import annotations

import logging
import re
import time
from pathlib import Path

from sqlalchemy import Engine, func, select
from sqlalchemy.exc import IntegrityError
from sqlalchemy.orm import Session, sessionmaker

from monoloc.core.errors import InvalidInputError
from monoloc.server.jobs.uploads import remove_tree
from monoloc.server.settings import Settings
from monoloc.server.storage.db import session_scope
from monoloc.server.storage.keys import KEY_PREFIX, PREFIX_CHARS, hash_api_key
from monoloc.server.storage.models import ApiKey, utc_now

log = logging.getLogger(__name__)
_BOOTSTRAP_RE = re.compile(rf"^{KEY_PREFIX}[A-Za-z0-9_-]{{32,200}}$")
INCOMING_PREFIX = ".incoming-"


def bootstrap_admin_key(sessions: sessionmaker[Session], settings: Settings) -> bool:
    """Store the configured bootstrap admin key if there is no key yet; True if stored."""
    if settings.bootstrap_admin_key is None:
        return False
    plaintext = settings.bootstrap_admin_key.get_secret_value().strip()
    if not plaintext:
        return False  # set but empty (e.g. an unset variable in compose.yaml)
    if not _BOOTSTRAP_RE.match(plaintext):
        raise InvalidInputError(
            f"MONOLOC_BOOTSTRAP_ADMIN_KEY must be '{KEY_PREFIX}' followed by at least 32 "
            'URL-safe characters (generate one with: python -c "import secrets; '
            f"print('{KEY_PREFIX}' + secrets.token_urlsafe(32))\")"
        )
    try:
        with session_scope(sessions) as session:
            if session.scalar(select(func.count(ApiKey.id))):
                return False
            session.add(
                ApiKey(
                    name="bootstrap",
                    prefix=plaintext[:PREFIX_CHARS],
                    key_hash=hash_api_key(plaintext),
                    scopes="admin",
                    created_at=utc_now(),
                )
            )
    except IntegrityError:
        # Another process stored the same key between our count and our insert (the
        # server start-up holds the database's start-up lock, so only a caller without
        # it gets here): the key is there, which is all this function promises.
        return False
    log.warning("stored the bootstrap admin key (prefix %s)", plaintext[:PREFIX_CHARS])
    return True


def prepare_database(settings: Settings) -> Engine:
    """Bring the schema up to date and store the bootstrap key, holding the database's
    start-up lock: replicas starting together take turns, the first does the work and
    the others find it done. Returns a new engine on the database."""
    from monoloc.server.storage.db import create_engine_for, make_session_factory, startup_lock
    from monoloc.server.storage.migrate import upgrade_database

    with startup_lock(settings.database_url):
        upgrade_database(settings.database_url, take_startup_lock=False)
        engine = create_engine_for(settings)
        bootstrap_admin_key(make_session_factory(engine), settings)
    return engine


def uploads_dir(settings: Settings) -> Path:
    assert settings.uploads_dir is not None
    return Path(settings.uploads_dir)


def clean_incoming_uploads(settings: Settings, older_than_s: float = 3600.0) -> int:
    """Delete half-received uploads a crash left in ``uploads/.incoming-*`` (only those
    untouched for ``older_than_s``: replicas share the directory, and another one may be
    receiving an upload right now)."""
    root = uploads_dir(settings)
    if not root.is_dir():
        return 0
    cutoff = time.time() - older_than_s
    stale = [
        p
        for p in root.iterdir()
        if p.name.startswith(INCOMING_PREFIX) and p.stat().st_mtime < cutoff
    ]
    for path in stale:
        remove_tree(path)
    return len(stale)
