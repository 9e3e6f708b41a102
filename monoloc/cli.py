"""`monoloc` console script. It only wires the sub-commands each package defines.

Each package keeps its own typer app in ``<package>/cli.py``; heavy imports stay inside
the command functions so ``monoloc --help`` is instant.
"""

from __future__ import annotations

import importlib
import sys

import typer

from monoloc.core.errors import MonolocError

app = typer.Typer(
    name="monoloc",
    help="Monocular visual localization for vehicles against a map of geo-tagged images.",
    no_args_is_help=True,
    pretty_exceptions_enable=False,
)

# (module, attribute, name, extra) of each sub-command group and command: ``extra`` is
# the install extra that brings the command's dependencies (a bare `pip install monoloc`
# is the vehicle library: `monoloc drive` only).
_GROUPS = [
    ("monoloc.server.cli", "vocab_app", "vocab", "server"),
    ("monoloc.server.cli", "db_app", "db", "server"),
    ("monoloc.server.cli", "map_app", "map", "server"),
    ("monoloc.server.cli", "keys_app", "keys", "server"),
    ("monoloc.server.shards_cli", "shards_app", "shards", "server"),
    ("monoloc.sim.cli", "app", "sim", "sim"),
]
_COMMANDS = [
    ("monoloc.server.cli", "localize", "localize", "server"),
    ("monoloc.server.cli", "serve", "serve", "server"),
    ("monoloc.client.cli", "drive", "drive", ""),
    ("monoloc.demo", "demo", "demo", "all"),
]


def _register() -> None:
    """Add every sub-command to ``app`` (once)."""
    if app.registered_groups or app.registered_commands:
        return
    for module_name, attr, name, _ in _GROUPS + _COMMANDS:
        module = importlib.import_module(module_name)
        obj = getattr(module, attr)
        if isinstance(obj, typer.Typer):
            app.add_typer(obj, name=name)
        else:
            app.command(name=name)(obj)


def _missing_extra_message(exc: ModuleNotFoundError, argv: list[str]) -> str | None:
    """One line naming the extra to install, when a command's dependency is missing."""
    if exc.name is None or exc.name.split(".")[0] == "monoloc":
        return None
    command = argv[1] if len(argv) > 1 else ""
    extra = next((e for _, _, name, e in _GROUPS + _COMMANDS if name == command), "all")
    if not extra:
        return None  # a vehicle command: its dependencies are required, so this is a bug
    return (
        f"error: `monoloc {command}` needs {exc.name!r}, which the bare vehicle install "
        f"leaves out: pip install 'monoloc[{extra}]'"
    )


# typer ships its own copy of click (``typer._click``) or uses click itself, depending on
# its version: take the exception class from typer's own BadParameter so both match.
_CLICK_EXCEPTION = next(c for c in typer.BadParameter.__mro__ if c.__name__ == "ClickException")


def _one_line(exc: Exception) -> str:
    """``error: <command>: <message> (see <command> --help)`` in one line."""
    message = " ".join(exc.format_message().split())
    ctx = getattr(exc, "ctx", None)
    if ctx is None:
        return f"error: {message}"
    return f"error: {ctx.command_path}: {message} (see {ctx.command_path} --help)"


def main() -> None:
    """Entry point: run the CLI, turning a MonolocError into one line and exit code 1."""
    _register()
    try:
        app(standalone_mode=False, prog_name="monoloc")
    except MonolocError as exc:
        typer.secho(f"error: {exc}", err=True, fg=typer.colors.RED)
        sys.exit(1)
    except ModuleNotFoundError as exc:
        message = _missing_extra_message(exc, sys.argv)
        if message is None:
            raise
        typer.secho(message, err=True, fg=typer.colors.RED)
        sys.exit(1)
    except (typer.Abort, KeyboardInterrupt):
        typer.secho("aborted", err=True)
        sys.exit(130)
    except typer.Exit as exc:
        sys.exit(exc.exit_code)
    except _CLICK_EXCEPTION as exc:  # usage errors (exit 2) and other click errors
        typer.secho(_one_line(exc), err=True, fg=typer.colors.RED)
        sys.exit(exc.exit_code)


if __name__ == "__main__":
    main()
