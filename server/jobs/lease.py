"""Jobs as leases in the database: any replica takes queued work, holds it while it
renews its lease, and work whose holder died is taken over. Never commits.

A job is *claimable* when it is ``queued``, or ``running`` with a lease that expired
(its holder stopped renewing: killed, frozen, cut off from the database). Claiming sets
``running``, the new owner, a fresh expiry and ``attempts + 1`` in one statement. On
PostgreSQL the candidate row is picked with ``FOR UPDATE SKIP LOCKED``, so replicas
claiming at once take different jobs without waiting on each other; on SQLite the
database's single writer makes the conditional UPDATE a compare-and-set. The holder
renews with ``UPDATE ... WHERE lease_owner = me AND state = 'running'``: zero rows means
the job was taken over or cancelled, and the holder stops without writing its outcome.
Every job kind is idempotent (entries by image hash, VLADs by vocabulary id), so work
taken over is resumed, never duplicated.

Owners are ``host:pid:random``; a restarted process on the same host (SQLite) finds the
leases of its dead predecessor by the pid and takes them over at once
(:func:`expire_dead_local_leases`) instead of waiting for them to expire.
"""

from __future__ import annotations

import os
import secrets
import socket
from datetime import timedelta

from sqlalchemy import and_, or_, select, update
from sqlalchemy.orm import Session

from monoloc.server.jobs.store import get_job
from monoloc.server.storage.models import Job, utc_now
from monoloc.server.storage.records import JobRecord


def new_owner_id() -> str:
    """``host:pid:random``: unique per process start."""
    return f"{socket.gethostname()[:64]}:{os.getpid()}:{secrets.token_hex(4)}"


def _claimable(now):
    # A running job without an owner is a foreground CLI job (jobs.lifecycle): never ours.
    expired = or_(Job.lease_expires_at.is_(None), Job.lease_expires_at < now)
    return or_(
        Job.state == "queued",
        and_(Job.state == "running", Job.lease_owner.is_not(None), expired),
    )


def claim_next_job(session: Session, owner: str, lease_s: float, kinds) -> JobRecord | None:
    """Take the oldest claimable job of one of ``kinds`` for ``owner``; None if none."""
    now = utc_now()
    pick = (
        select(Job.id).where(_claimable(now), Job.kind.in_(list(kinds))).order_by(Job.id).limit(1)
    )
    if session.get_bind().dialect.name == "postgresql":
        pick = pick.with_for_update(skip_locked=True)
    job_id = session.scalar(pick)
    if job_id is None:
        return None
    claimed = session.execute(
        update(Job)
        .where(Job.id == job_id, _claimable(now))
        .values(
            state="running",
            lease_owner=owner,
            lease_expires_at=now + timedelta(seconds=lease_s),
            attempts=Job.attempts + 1,
            finished_at=None,
            error=None,
            message="started",
            updated_at=now,
        )
        .execution_options(synchronize_session=False)
    )
    if claimed.rowcount != 1:
        return None  # another process won the race (SQLite): try again next poll
    return get_job(session, job_id)


def renew_lease(session: Session, job_id: int, owner: str, lease_s: float) -> bool:
    """Extend ``owner``'s lease; False if the job is no longer ours and running."""
    now = utc_now()
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.lease_owner == owner, Job.state == "running")
        .values(lease_expires_at=now + timedelta(seconds=lease_s))
        .execution_options(synchronize_session=False)
    )
    return result.rowcount == 1


def holds_lease(session: Session, job_id: int, owner: str) -> bool:
    """True while ``owner`` holds the running job's lease (lock the row on PostgreSQL)."""
    stmt = select(Job.id).where(Job.id == job_id, Job.lease_owner == owner, Job.state == "running")
    if session.get_bind().dialect.name == "postgresql":
        stmt = stmt.with_for_update()
    return session.scalar(stmt) is not None


def hand_back(session: Session, job_id: int, owner: str) -> bool:
    """Put ``owner``'s running job back in the queue (a graceful shutdown): any replica,
    or this process restarted, takes it over at once."""
    result = session.execute(
        update(Job)
        .where(Job.id == job_id, Job.lease_owner == owner, Job.state == "running")
        .values(
            state="queued",
            lease_owner=None,
            lease_expires_at=None,
            message="handed back by a stopping server; waiting for a replica",
            updated_at=utc_now(),
        )
        .execution_options(synchronize_session=False)
    )
    return result.rowcount == 1


def _pid_alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def expire_dead_local_leases(session: Session) -> list[int]:
    """Expire the leases held by processes of this host that no longer exist (a crash
    before this restart); returns the job ids, now claimable."""
    host = socket.gethostname()[:64]
    rows = session.execute(
        select(Job.id, Job.lease_owner).where(
            Job.state == "running", Job.lease_owner.like(f"{host}:%")
        )
    ).all()
    dead = []
    for job_id, owner in rows:
        parts = owner.split(":")
        if len(parts) == 3 and parts[1].isdigit() and not _pid_alive(int(parts[1])):
            dead.append(job_id)
    if dead:
        session.execute(
            update(Job)
            .where(Job.id.in_(dead))
            .values(lease_expires_at=None)
            .execution_options(synchronize_session=False)
        )
    return dead
