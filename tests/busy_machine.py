"""Deadlines and waits of the servers the tests start, generous enough for a loaded
machine (``make test`` on 2 shared cores): a test whose subject is not time must not
fail because a frame waited 2 s for a CPU. The tests of admission, deadlines and leases
set their own values over these (tests directories are not packages: a module name of
its own)."""

from __future__ import annotations

GENEROUS_DEADLINES: dict[str, int | float] = dict(
    localize_deadline_ms=120_000,  # the product's 2 s is the admission tests' subject
    write_deadline_ms=300_000,
    busy_timeout_ms=60_000,  # SQLite's write lock
    job_lease_s=120.0,  # renewed every 40 s: a starved renewal does not lose the job
)


def generous_env() -> dict[str, str]:
    """The same values as ``MONOLOC_*`` variables, for servers run as processes."""
    return {f"MONOLOC_{name.upper()}": str(value) for name, value in GENEROUS_DEADLINES.items()}
