"""Alembic environment and revisions of the monoloc map database (shipped as a package)."""
