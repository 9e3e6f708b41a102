"""`monoloc demo`: a sim city, a map server, a car localizing against it, numbers and plots.

1. generate a small sim city (train, map, query, night, nightmap runs);
2. start the server on localhost (or use --server/--key);
3. train a vocabulary on the train run (a scratch map), create the map with it, calibrate
   the measurement model on the train run, upload the map run;
4. drive the query run over the WebSocket with the client's particle filter; then the
   night run twice: before and after an operator adds night images (admin route);
   then a short closed-loop drive: the sim's 1:10 car maps part of the indoor track and
   steers on monoloc's estimate (``monoloc.sim.closed_loop_study``);
5. print a table beside the paper's numbers; 6. write PNG plots and summary.json;
7. print the operator's console URL (``/ui``) and, with ``--serve`` (the default when run
   in a terminal), keep the server running until Ctrl-C.
"""

from __future__ import annotations

import json
import shutil
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import typer

PAPER = {"position_rmse_m": 0.313, "rate_hz": 10.0}


@dataclass(frozen=True)
class DemoConfig:
    out_dir: Path = Path("out/demo")
    frames: int = 200
    size: str = "small"
    seed: int = 3
    server: str | None = None
    key: str | None = None
    serve: bool = False  # keep the server up at the end until interrupted
    closed_loop_frames: int = 100  # the closed-loop lap's frames (0: no closed-loop lap)


def demo(
    out: Path = typer.Option(Path("out/demo"), help="where data, plots and results go"),
    frames: int = typer.Option(200, help="frames per sim run"),
    seed: int = typer.Option(3, help="seed of the sim city"),
    server: str | None = typer.Option(None, help="use this server instead of starting one"),
    key: str | None = typer.Option(None, envvar="MONOLOC_API_KEY", help="admin key for --server"),
    closed_loop_frames: int = typer.Option(
        100, help="frames of the short closed-loop drive on the indoor track (0: skip it)"
    ),
    serve: bool | None = typer.Option(
        None,
        "--serve/--no-serve",
        help="keep serving the console (URL/ui) until Ctrl-C; default: when run in a terminal",
    ),
) -> None:
    """Generate a sim city, map it, localize a car in it; print a table and write plots."""
    if serve is None:
        serve = sys.stdin.isatty() and sys.stdout.isatty()
    config = DemoConfig(
        out_dir=out,
        frames=frames,
        seed=seed,
        server=server,
        key=key,
        serve=serve,
        closed_loop_frames=closed_loop_frames,
    )
    run_demo(config)


def _serve_until_interrupted(console, key: str) -> None:
    """Keep the demo's server running for the operator until Ctrl-C."""
    console.print(f"sign in with the demo's admin key {key}; Ctrl-C stops the server")
    try:
        while True:
            time.sleep(3600)
    except KeyboardInterrupt:
        console.print("stopping the map server")


def run_demo(config: DemoConfig) -> dict:
    from rich.console import Console

    from monoloc import local_server
    from monoloc.client.api import MonolocClient
    from monoloc.demo.steps import DemoSteps

    console = Console()
    started = time.monotonic()
    out = config.out_dir
    out.mkdir(parents=True, exist_ok=True)
    steps = DemoSteps(config, console)
    dataset = steps.generate()
    proc = None
    if config.server:
        if not config.key:
            raise local_server.LocalServerError("--server needs --key (an admin key)")
        url, key = config.server.rstrip("/"), config.key
    else:
        port, key = local_server.free_port(), local_server.new_admin_key()
        url = f"http://127.0.0.1:{port}"
        console.print(f"[bold]2[/] starting the map server on {url} (log: {out / 'server.log'})")
        # The demo's own server starts empty each run: it builds its map anew, and a
        # previous run's database would hold that run's admin key, not this one's.
        shutil.rmtree(out / "server", ignore_errors=True)
        proc = local_server.start_server(out / "server", port, key, out / "server.log")
    try:
        with MonolocClient(url, key, timeout_s=120.0) as client:
            map_id = steps.build_map(client, dataset)
            results = steps.drive_all(client, map_id, dataset)
            closed_loop = None
            if config.closed_loop_frames > 0:
                closed_loop = steps.closed_loop_lap(client)
            summary = steps.report(client, map_id, dataset, results, time.monotonic() - started)
            if closed_loop is not None:
                summary["closed_loop"] = closed_loop
                summary["plots"] += closed_loop["plots"]
        console.print(f"operator's console: {url}/ui#/maps/{map_id} (API docs: {url}/docs)")
        if config.serve and proc is not None:
            _serve_until_interrupted(console, key)
    finally:
        if proc is not None:
            local_server.stop_server(proc)
    (out / "summary.json").write_text(json.dumps(summary, indent=2, default=float) + "\n")
    console.print(f"summary: {out / 'summary.json'}; plots: {', '.join(summary['plots'])}")
    console.print(f"total {summary['total_s']:.0f} s")
    return summary
