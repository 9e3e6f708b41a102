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
        "map,query,train,night,offcenter; indoor: map,query,train,offcenter)",
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
) -> None:
    """Generate a city (KITTI odometry layout) or rooms with a race track (TUM RGB-D
    layout, one folder per run), drive the runs, and write dataset.json."""
    from rich.console import Console
    from rich.progress import BarColumn, MofNCompleteColumn, Progress, TimeRemainingColumn

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
