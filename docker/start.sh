#!/bin/sh
# Start the monoloc map server: bring the database schema up to date, then replace this
# shell with uvicorn (so it receives SIGTERM directly and shuts down gracefully: running
# jobs end 'interrupted', indexes are persisted).
#
# Environment: MONOLOC_HOST (default 0.0.0.0), MONOLOC_PORT (8000), MONOLOC_DATA_DIR,
# MONOLOC_DATABASE_URL and every other MONOLOC_* setting (monoloc.server.settings);
# MONOLOC_PYTHON picks the interpreter (default: python3 on PATH).
# Each process is a replica: its own index of every map, kept current from the database's
# change log; jobs are leases in the database that any replica may take.
set -eu

PYTHON="${MONOLOC_PYTHON:-python3}"
HOST="${MONOLOC_HOST:-0.0.0.0}"
PORT="${MONOLOC_PORT:-8000}"

# Multipart uploads are spooled to TMPDIR before they are unpacked: point it at a volume
# with room for the largest upload (compose.yaml uses /shared/tmp, the volume of
# MONOLOC_UPLOADS_DIR; the image makes /data and /shared its user's).
if [ -n "${TMPDIR:-}" ]; then mkdir -p "$TMPDIR"; fi

# With several replicas the schema is migrated once, before they start (compose.yaml's
# migrate service): they set MONOLOC_SKIP_MIGRATIONS=1.
if [ "${MONOLOC_SKIP_MIGRATIONS:-0}" != "1" ]; then
    "$PYTHON" -m monoloc.cli db upgrade
fi
exec "$PYTHON" -m uvicorn --factory monoloc.server.api.app:create_app_from_env \
    --host "$HOST" --port "$PORT" --workers 1 --timeout-graceful-shutdown 30
