"""Alembic revisions of the monoloc map database."""
