"""`monoloc sim ...`: generate a synthetic dataset, preview one."""

from __future__ import annotations

from pathlib import Path

import typer

app = typer.Typer(
    help="The synthetic KITTI-like world: generate datasets, preview them.", no_args_is_help=True
)


@app.command()
def generate(
    out: Path = typer.Option(..., "--out", help="dataset root to write"),
    scenario: str = typer.Option(
        "urban", help="urban (KITTI layout) | indoor (TUM RGB-D layout, 1:10 car in a room)"
    ),
    size: str = typer.Option("small", help="small | medium | large"),
    seed: int = typer.Option(0, help="seed: same seed, same bytes"),
    runs: str | None = typer.Option(
        None,
        help="comma-separated runs, one sequence each, in this order (default urban: "
        "map,query,train,night,offcenter; indoor: map,query,train,offcenter; urban also "
        "nightmap, trainnight, fleet)",
    ),
    frames: int | None = typer.Option(None, help="at most this many frames per run"),
    scale: float = typer.Option(1.0, help="image scale (1 = KITTI 1241x376 / D435 640x480)"),
    query_lighting: str = typer.Option("day", help="lighting of the query run: day|dusk|night"),
    depth: bool = typer.Option(
        False,
        help="also write exact depth maps under sequences/NN/depth/ (uint16 PNG, metres * 256)",
    ),
    stereo: bool = typer.Option(
        False,
        help="urban: also render the right camera (sequences/NN/image_1/, KITTI's 0.54 m "
        "baseline, P1 in calib.txt) for `map ingest --depth-from stereo`; about doubles "
        "the rendering time",
    ),
    no_errors: bool = typer.Option(False, help="exact geometry: no recording errors"),
    workers: int = typer.Option(1, help="worker processes (runs are rendered in chunks)"),
    fleet_camera: str = typer.Option(
        "issue48",
        help="urban: the camera of the `fleet` run (the query's drive by a fleet car's own "
        "camera): issue48 (1024x576, f 640 px, plumb_bob), issue48_equidistant, "
        "issue48_pinhole",
    ),
) -> None:
    """Generate a city (KITTI odometry layout) or rooms with a race track (TUM RGB-D
    layout, one folder per run), drive the runs, and write dataset.json."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

    from monoloc.sim.fleet_camera import FleetCameraConfig
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.recording import RecordingErrors
    from monoloc.sim.summary import frames_per_second_note

    config = GenerateConfig(
        scenario=scenario,
        size=size,
        seed=seed,
        runs=tuple(r.strip() for r in (runs or _default_runs(scenario)).split(",") if r.strip()),
        max_frames=frames,
        image_scale=scale,
        write_depth=depth,
        write_stereo=stereo,
        query_lighting=query_lighting,
        errors=RecordingErrors.none() if no_errors else RecordingErrors(),
        workers=workers,
        fleet_camera=FleetCameraConfig.preset(fleet_camera),
    )
    config.validate()
    console = Console(stderr=True)
    tasks: dict[str, int] = {}
    with Progress(
        "[progress.description]{task.description}",
        BarColumn(),
        MofNCompleteColumn(),
        TimeRemainingColumn(),
        console=console,
    ) as bar:

        def progress(seq_id: str, done: int, total: int) -> None:
            if seq_id not in tasks:
                tasks[seq_id] = bar.add_task(f"sequence {seq_id}", total=total)
            bar.update(tasks[seq_id], completed=done)

        summary = generate_dataset(config, out, progress=progress)
    for s in summary.sequences:
        console.print(
            f"{s.seq_id}  {s.kind:<9} {s.lighting:<5} {s.frames:5d} frames  "
            f"route {s.length_m:7.1f} m"
        )
    console.print(f"wrote {out} ({frames_per_second_note(summary)})")


def _default_runs(scenario: str) -> str:
    return (
        "map,query,train,offcenter" if scenario == "indoor" else "map,query,train,night,offcenter"
    )


@app.command()
def preview(
    dataset: Path = typer.Argument(..., help="dataset root written by `monoloc sim generate`"),
    out: Path | None = typer.Option(None, help="PNG to write (default DATASET/preview.png)"),
    per_run: int = typer.Option(4, help="frames per run on the contact sheet"),
) -> None:
    """A PNG with a top-down map of the routes and a contact sheet of frames."""
    from monoloc.sim.preview import write_preview

    path = write_preview(dataset, out or dataset / "preview.png", per_run)
    typer.echo(f"wrote {path}")


@app.command("closed-loop")
def closed_loop(
    out: Path = typer.Option(Path("out/closed_loop"), help="where runs, results and plots go"),
    scenario: str = typer.Option("indoor", help="indoor (the 1:10 track)"),
    size: str = typer.Option("small", help="small | medium | large"),
    seed: int = typer.Option(0, help="seed of the world"),
    mode: str = typer.Option("closed", help="closed (steer on the estimate) | open (on the truth)"),
    controller: str = typer.Option(
        "pid",
        help="pid | mpc (the localization-aware model predictive controller, sim/mpc.py) "
        "for the drive; mapping laps are driven by the PID",
    ),
    laps: float = typer.Option(1.0, help="laps of the reference path to drive"),
    frames: int | None = typer.Option(None, help="at most this many camera frames"),
    map_laps: float | None = typer.Option(
        None, help="centre-line mapping laps when building a map (default: indoor 1, urban --laps)"
    ),
    offcenter_laps: float = typer.Option(
        0.0, help="oscillating off-center laps added to the map before driving (0: none)"
    ),
    train_laps: float | None = typer.Option(
        None,
        help="training laps for the calibration, 0: the default measurement model "
        "(default: indoor 1.5, urban 0.15 of the training route)",
    ),
    latency_from: Path | None = typer.Option(
        None, help="frames.csv of an earlier drive: draw answer delays from its latencies"
    ),
    server: str | None = typer.Option(None, help="use this server instead of starting one"),
    key: str | None = typer.Option(None, envvar="MONOLOC_API_KEY", help="key for --server"),
    map_name: str | None = typer.Option(
        None, "--map", help="drive against this existing map (with --server) instead of mapping"
    ),
) -> None:
    """One closed-loop (or open-loop) drive through the map server: map the track (or use
    --map), drive, write the run (TUM layout), the estimate, frames.csv, summary.json and
    a plot under OUT."""
    import json

    from monoloc.client.api import MonolocClient
    from monoloc.core.errors import InvalidInputError
    from monoloc.sim.closed_loop import CONTROLLERS, MODES
    from monoloc.sim.closed_loop_metrics import loop_metrics
    from monoloc.sim.closed_loop_plots import plot_cases
    from monoloc.sim.closed_loop_record import write_loop_outputs
    from monoloc.sim.closed_loop_study import (
        StudyConfig,
        add_offcenter,
        build_map,
        drive_case,
        read_latencies,
        serving,
    )
    from monoloc.sim.closed_loop_world import WorldSpec, build_loop_world

    if mode not in MODES:
        raise InvalidInputError(f"--mode must be one of {MODES}, got {mode!r}")
    if controller not in CONTROLLERS:
        raise InvalidInputError(f"--controller must be one of {CONTROLLERS}, got {controller!r}")
    if map_name is not None and server is None:
        raise InvalidInputError("--map needs --server (a server that holds that map)")
    if laps <= 0:
        raise InvalidInputError("--laps must be positive")
    if frames is not None and frames < 1:
        raise InvalidInputError("--frames must be at least 1")
    recorded = read_latencies(latency_from) if latency_from is not None else None
    world = build_loop_world(WorldSpec(scenario, size, seed))
    for n in (laps, map_laps, offcenter_laps or None, train_laps or None):
        if n is not None:  # refused here, before a server is started (e.g. > 1 city route)
            world.reference_path(n, "main")
    if map_laps is None:
        map_laps = 1.0 if scenario == "indoor" else laps
    if train_laps is None:
        train_laps = 1.5 if scenario == "indoor" else 0.15
    study = StudyConfig(
        laps=laps,
        map_laps=map_laps,
        offcenter_laps=offcenter_laps,
        train_laps=train_laps,
        max_frames=frames,
        seed=seed,
        cases=("open",),
    )
    with serving(out, server, key) as (url, api_key):
        with MonolocClient(url, api_key, timeout_s=120.0) as client:
            if map_name is not None:
                map_id = client.find_map_id(map_name)
            else:
                typer.echo(f"mapping the {scenario} track on {url}")
                map_id, _ = build_map(client, world, study, out, log=typer.echo)
                if offcenter_laps > 0:
                    add_offcenter(client, map_id, world, study, out, log=typer.echo)
            typer.echo(f"driving {laps:g} lap(s), {mode} loop, {controller}, against map {map_id}")
            result = drive_case(
                client,
                map_id,
                world,
                mode,
                study,
                recorded,
                record_dir=out / "drive" / "run",
                controller=controller,
            )
    metrics = loop_metrics(result)
    summary = {
        "mode": mode,
        "controller": controller,
        "scenario": scenario,
        "map_id": map_id,
        **metrics,
    }
    write_loop_outputs(result, out / "drive", summary)
    plots = plot_cases(
        {mode if mode == "open" else "closed": result},
        out,
        prefix="drive",
        reference_xy=world.reference_path(laps).xy,
    )
    typer.echo(json.dumps({k: summary[k] for k in _SHOWN if k in summary}, default=float))
    typer.echo(f"wrote {out / 'drive'} and {', '.join(str(p) for p in plots)}")


_SHOWN = (
    "frames",
    "loc_rmse_m",
    "loc_p95_m",
    "loc_max_m",
    "lateral_rmse_m",
    "lateral_max_m",
    "lane_departures",
    "hypotheses_share",
    "corr_tracking_vs_loc_error",
)
