"""`monoloc` console script. It only wires the sub-commands each package defines.

Each package keeps its own typer app in ``<package>/cli.py``; heavy imports stay inside
the command functions so ``monoloc --help`` is instant.
"""

from __future__ import annotations

import importlib
import sys

import typer

from client.errors import MonolocError

app = typer.Typer(
    name="monoloc",
    help="Monocular visual localization for vehicles against a map of geo-tagged images.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)

# (module, attribute, name) of each sub-command group; a module that does not exist yet
# is skipped so partial checkouts still run.
_GROUPS = [
    ("server.cli", "vocab_app", "vocab"),
    ("server.cli", "db_app", "db"),
    ("server.cli", "map_app", "map"),
    ("server.cli", "keys_app", "keys"),
    ("sim.cli", "app", "sim"),
]
_COMMANDS = [
    ("server.cli", "localize", "localize"),
    ("server.cli", "serve", "serve"),
    ("client.cli", "drive", "drive"),
    ("monoloc.demo", "demo", "demo"),
]


def _register() -> None:
    for module_name, attr, name in _GROUPS + _COMMANDS:
        try:
            module = importlib.import_module(module_name)
        except ModuleNotFoundError as exc:
            if exc.name and module_name.startswith(exc.name):
                continue
            raise
        obj = getattr(module, attr, None)
        if obj is None:
            continue
        if isinstance(obj, typer.Typer):
            app.add_typer(obj, name=name)
        else:
            app.command(name=name)(obj)


def main() -> None:
    """Entry point: run the CLI, turning a MonolocError into one line and exit code 1."""
    _register()
    try:
        app(standalone_mode=False)
    except MonolocError as exc:
        typer.secho(f"error: {exc}", err=True, fg=typer.colors.RED)
        sys.exit(1)
    except (typer.Abort, KeyboardInterrupt):
        typer.secho("aborted", err=True)
        sys.exit(130)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except Exception as exc:  # click usage errors carry their own exit code
        import click

        if isinstance(exc, click.ClickException):
            exc.show()
            sys.exit(exc.exit_code)
        raise


if __name__ == "__main__":
    main()
