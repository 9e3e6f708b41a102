"""Command-line sub-apps of the map server, wired into `monoloc` by monoloc/cli.py.

Commands only parse arguments and call one typed function; heavy imports (OpenCV, FAISS,
scikit-image) happen inside the commands so `monoloc --help` stays instant.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

from monoloc.server.api.cli import keys_app, serve  # noqa: F401  (wired by monoloc/cli.py)

vocab_app = typer.Typer(help="Visual vocabulary: retrain the shipped 64-word default.")


@vocab_app.callback()
def _vocab() -> None:
    """Visual vocabulary commands (a group even while it has a single command)."""


@vocab_app.command("train")
def vocab_train(
    out: Annotated[Path, typer.Option(help="Where to write the vocabulary .npz.")] = Path(
        "server/vision/data/default_vocabulary.npz"
    ),
    seed: Annotated[int, typer.Option(help="k-means seed.")] = 0,
    n_iter: Annotated[int, typer.Option(help="k-means iterations.")] = 20,
) -> None:
    """Retrain the default vocabulary on augmented scikit-image photographs."""
    from monoloc.server.vision.default_vocab import train_default_vocabulary
    from monoloc.server.vision.vocabulary import VocabularyConfig, save_vocabulary

    vocabulary = train_default_vocabulary(vocabulary=VocabularyConfig(seed=seed, n_iter=n_iter))
    out.parent.mkdir(parents=True, exist_ok=True)
    save_vocabulary(out, vocabulary)
    typer.echo(f"wrote {out} (version {vocabulary.version})")
    typer.echo(vocabulary.description)


db_app = typer.Typer(help="Map database: schema upgrades (Alembic).", no_args_is_help=True)

DatabaseUrlOption = Annotated[
    str | None,
    typer.Option(help="SQLAlchemy URL; default MONOLOC_DATABASE_URL or <data_dir>/monoloc.db."),
]


def _database_url(database_url: str | None) -> str:
    from monoloc.server.settings import get_settings

    return database_url or get_settings().database_url


@db_app.command("upgrade")
def db_upgrade(database_url: DatabaseUrlOption = None) -> None:
    """Create or upgrade the database schema to the newest revision."""
    from monoloc.server.storage.db import redact_url
    from monoloc.server.storage.migrate import current_revision, upgrade_database

    url = _database_url(database_url)
    upgrade_database(url)
    typer.echo(f"{redact_url(url)}: at revision {current_revision(url)}")


@db_app.command("current")
def db_current(database_url: DatabaseUrlOption = None) -> None:
    """Print the database's schema revision ('none' if not created yet) and the newest."""
    from monoloc.server.storage.migrate import current_revision, head_revision

    url = _database_url(database_url)
    current, head = current_revision(url), head_revision()
    status = "up to date" if current == head else "run `monoloc db upgrade`"
    typer.echo(f"{current or 'none'} (head {head}: {status})")


# `monoloc map ...` lives in server/map_cli.py, `monoloc localize` in server/localize_cli.py.
from monoloc.server.localize_cli import localize  # noqa: E402, F401
from monoloc.server.map_cli import map_app  # noqa: E402, F401
