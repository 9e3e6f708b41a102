"""The map database: SQLAlchemy models, engine/session set-up, Alembic upgrades, repositories.

Modules: ``models`` (schema), ``db`` (engine with SQLite pragmas, sessions), ``migrate``
(Alembic upgrade), ``arrays`` (numpy <-> blob), ``records`` (plain results), and the
repositories ``maps``, ``entries``, ``runs``, ``keys`` (the jobs table's is
``monoloc.server.jobs.store``). Nothing is imported here so that
``import monoloc.server.storage`` stays cheap.
"""
