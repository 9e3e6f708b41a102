"""``monoloc map ...``: parse arguments, call one typed function, print. Re-exported by
``server/cli.py`` (``map_app``); ``monoloc localize`` is in server/localize_cli.py.

Every command works on the database of the settings (``MONOLOC_DATA_DIR`` /
``MONOLOC_DATABASE_URL``; ``--data-dir`` overrides the data directory) and upgrades its
schema first. Heavy imports happen inside the commands.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated

import typer

map_app = typer.Typer(
    help="Maps: create, ingest runs, import/export COLMAP and kapture, vocabulary, calibration, "
    "statistics.",
    no_args_is_help=True,
)

DataDir = Annotated[
    Path | None,
    typer.Option(
        "--data-dir",
        help="Data directory (database + indexes); default MONOLOC_DATA_DIR or ./data.",
    ),
]
MapRef = Annotated[str, typer.Option("--map", "-m", help="Map name or id.")]


def open_database(ctx: typer.Context | None, data_dir: Path | None = None):
    """(settings, session factory) with the schema upgraded."""
    from monoloc.server.settings import get_settings
    from monoloc.server.storage.db import create_engine_for, make_session_factory
    from monoloc.server.storage.migrate import upgrade_database

    if data_dir is None and ctx is not None:
        data_dir = (ctx.obj or {}).get("data_dir")
    settings = get_settings(data_dir=data_dir) if data_dir else get_settings()
    upgrade_database(settings.database_url)
    return settings, make_session_factory(create_engine_for(settings))


@map_app.callback()
def _map(ctx: typer.Context, data_dir: DataDir = None) -> None:
    """Map commands."""
    ctx.obj = {"data_dir": data_dir}


@map_app.command("create")
def map_create(
    ctx: typer.Context,
    name: Annotated[str, typer.Argument(help="Map name (letters, digits, . _ -).")],
    camera: Annotated[
        str | None,
        typer.Option(
            help="kitti | freiburg1|2|3 | <calib.txt> | <KITTI sequence or TUM run folder> | "
            "<camera.json>"
        ),
    ] = None,
    fx: float | None = None,
    fy: float | None = None,
    cx: float | None = None,
    cy: float | None = None,
    width: int | None = None,
    height: int | None = None,
    vocabulary: Annotated[str, typer.Option(help="default | vocabulary id | hash")] = "default",
) -> None:
    """Create an empty map with a camera and a vocabulary."""
    from monoloc.server.ingest.manage import CameraOverrides, camera_from_spec, create_map

    _, factory = open_database(ctx)
    intrinsics = camera_from_spec(camera, CameraOverrides(fx, fy, cx, cy, width, height))
    record = create_map(factory, name, intrinsics, vocabulary)
    typer.echo(
        f"created map {record.name} (id {record.id}), camera {intrinsics}, "
        f"vocabulary {record.vocabulary_hash}"
    )


@map_app.command("list")
def map_list(ctx: typer.Context) -> None:
    """List the maps."""
    from rich.console import Console
    from rich.table import Table

    from monoloc.server.ingest.manage import list_maps

    _, factory = open_database(ctx)
    from monoloc.server.vision.features import rule_is_current, rule_text

    table = Table(
        "id", "name", "entries", "version", "vocabulary", "camera", "calibrated", "corners"
    )
    stale = []
    for m in list_maps(factory):
        c = m.camera
        current = rule_is_current(m.features)
        stale += [] if current else [m.name]
        table.add_row(
            str(m.id),
            m.name,
            str(m.n_entries),
            str(m.version),
            m.vocabulary_hash,
            f"{c.width_px}x{c.height_px} f={c.fx:.1f}",
            "yes" if m.calibration else "no",
            rule_text(m.features) + ("" if current else " (not the default)"),
        )
    Console().print(table)
    if stale:
        typer.echo(
            f"{', '.join(stale)}: entries picked their ORB corners by another rule than the "
            "default; served by their own rule, upload the runs again into a new map to "
            "rebuild with the default"
        )


@map_app.command("stats")
def map_stats(
    ctx: typer.Context, map_ref: Annotated[str, typer.Argument(help="Map name or id.")]
) -> None:
    """Entries, runs, tags, version, vocabulary, calibration, 3D keypoints per entry."""
    from monoloc.server.ingest.manage import map_stats as compute
    from monoloc.server.ingest.report import print_stats

    _, factory = open_database(ctx)
    print_stats(compute(factory, map_ref))


@map_app.command("ingest")
def map_ingest(
    ctx: typer.Context,
    path: Annotated[Path, typer.Argument(help="KITTI dataset root or sequence; TUM run; ROS bag.")],
    map_ref: MapRef,
    fmt: Annotated[str, typer.Option("--format", help="kitti | tum | rosbag")] = "kitti",
    sequence: Annotated[str | None, typer.Option(help="KITTI sequence (NN).")] = None,
    frames: Annotated[
        str | None, typer.Option(help="Frame range A:B (Python slice: 0:3860 = frames 0..3859).")
    ] = None,
    tags: Annotated[str, typer.Option(help="Comma-separated tags, e.g. night.")] = "",
    kind: Annotated[str, typer.Option(help="Run kind: map | offcenter | night | ...")] = "map",
    skip_bad_frames: Annotated[
        bool, typer.Option(help="Skip unreadable images/scans (reported) instead of failing.")
    ] = False,
    workers: Annotated[int, typer.Option(help="Threads building entries.")] = 2,
    camera: Annotated[str | None, typer.Option(help="TUM: freiburg1|2|3|default.")] = None,
    depth_from: Annotated[
        str,
        typer.Option(
            help="KITTI: where keypoint depth comes from: lidar (velodyne/) or stereo "
            "(the right camera image_1/ and P1 of calib.txt; no LiDAR needed)."
        ),
    ] = "lidar",
    fx: float | None = None,
    fy: float | None = None,
    cx: float | None = None,
    cy: float | None = None,
    width: int | None = None,
    height: int | None = None,
    topic: Annotated[
        list[str] | None,
        typer.Option(
            help="rosbag: ROLE=TOPIC (roles image, camera_info, depth, cloud, pose); "
            "repeatable; a role left out is found by message type."
        ),
    ] = None,
    register: Annotated[
        bool,
        typer.Option(
            help="Register the run to the map's entries first (localize its frames near "
            "their written poses, move its poses by the smoothed difference)."
        ),
    ] = False,
) -> None:
    """Ingest a KITTI sequence, a TUM RGB-D run or a ROS 2 bag into a map (idempotent,
    resumable)."""
    from monoloc.core.registration import RegistrationConfig
    from monoloc.server.entry_builder import BuildConfig
    from monoloc.server.ingest.common import parse_frame_range
    from monoloc.server.ingest.manage import (
        CameraOverrides,
        find_map,
        ingest_source,
        open_source,
    )
    from monoloc.server.ingest.pipeline import IngestConfig
    from monoloc.server.ingest.report import print_ingest_summary, progress_bar

    _, factory = open_database(ctx)
    intrinsics = CameraOverrides(fx, fy, cx, cy, width, height).complete()
    if depth_from == "none":
        raise typer.BadParameter(
            "a mapping run needs depth: lidar or stereo", param_hint="--depth-from"
        )
    # a bag without CameraInfo was recorded by the map's camera
    map_camera = find_map(factory, map_ref).camera if fmt == "rosbag" else None
    source = open_source(
        fmt,
        path,
        sequence=sequence,
        frames=parse_frame_range(frames),
        camera=intrinsics,
        tum_camera=camera,
        topics=parse_topics(topic),
        depth_from=depth_from,
        map_camera=map_camera,
    )
    config = IngestConfig(
        build=BuildConfig(),
        workers=workers,
        skip_bad_frames=skip_bad_frames,
        register=RegistrationConfig() if register else None,
    )
    tag_list = tuple(t.strip() for t in tags.split(",") if t.strip())
    with progress_bar(f"ingesting {source.name}") as update:
        summary = ingest_source(
            factory, map_ref, source, kind=kind, tags=tag_list, config=config, progress=update
        )
    print_ingest_summary(summary)


def job_params(model, **values):
    """``model.create(**values)`` (a job's parameters, monoloc.server.jobs.params); a bad
    value is a usage error naming its option."""
    from pydantic import ValidationError

    from monoloc.core.errors import InvalidInputError

    try:
        return model.create(**values)
    except InvalidInputError as exc:
        cause = exc.__cause__
        errors = cause.errors() if isinstance(cause, ValidationError) else []
        options = ["--" + str(e["loc"][0]).replace("_", "-") for e in errors if e["loc"]]
        why = "; ".join(e["msg"].removeprefix("Value error, ") for e in errors)
        raise typer.BadParameter(why or str(exc), param_hint=options or None) from None


def parse_topics(items: list[str] | None) -> dict[str, str]:
    """The ``--topic ROLE=TOPIC`` values as a dict (a usage error otherwise)."""
    from monoloc.core.formats.rosbag import parse_topic_options

    try:
        return parse_topic_options(items)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None


@map_app.command("vocab")
def map_vocab(
    ctx: typer.Context,
    map_ref: MapRef,
    train_from: Annotated[Path | None, typer.Option(help="Run to train a vocabulary on.")] = None,
    fmt: Annotated[str, typer.Option("--format", help="kitti | tum")] = "kitti",
    sequence: str | None = None,
    frames: str | None = None,
    vocabulary: Annotated[
        str | None,
        typer.Option(help="Switch to an existing vocabulary (id, hash or default) instead."),
    ] = None,
    max_images: Annotated[
        int | None, typer.Option(help="Images of the run to train on (default: the training's).")
    ] = None,
    seed: Annotated[
        int | None, typer.Option(help="k-means seed (default: the training's).")
    ] = None,
) -> None:
    """Train a vocabulary (k=64) from a run and/or switch the map to it (a recorded job:
    every entry's VLAD and code is recomputed)."""
    from monoloc.server.ingest.common import parse_frame_range
    from monoloc.server.ingest.manage import open_source
    from monoloc.server.ingest.report import progress_bar
    from monoloc.server.jobs.vocabulary import (
        VocabularyParams,
        VocabularyTraining,
        run_vocabulary_job,
    )

    _, factory = open_database(ctx)
    if (train_from is None) == (vocabulary is None):
        raise typer.BadParameter("give exactly one of --train-from and --vocabulary")
    train = None
    if train_from is not None:
        train = job_params(
            VocabularyTraining, run=str(train_from), max_images=max_images, seed=seed
        )
    params = job_params(VocabularyParams, vocabulary=vocabulary, train=train)
    source = None
    if train_from is not None:
        source = open_source(
            fmt,
            train_from,
            sequence=sequence,
            frames=parse_frame_range(frames),
            tum_camera="default",
            depth_from="none",  # a vocabulary is trained on images only
        )
    with progress_bar("recomputing VLADs") as update:
        job, change = run_vocabulary_job(factory, map_ref, params, source=source, progress=update)
    typer.echo(
        f"job {job.id} {job.state}: map {change.map_id} now on vocabulary "
        f"{change.vocabulary_id}; {change.recomputed} entries recomputed "
        f"({change.exact} from their images, {change.approximate} from stored "
        f"descriptors); map version {change.map_version}"
    )


@map_app.command("calibrate")
def map_calibrate(
    ctx: typer.Context,
    map_ref: MapRef,
    run: Annotated[
        Path, typer.Option("--run", help="Training run (not the test run): KITTI or TUM.")
    ],
    fmt: Annotated[str, typer.Option("--format", help="kitti | tum")] = "kitti",
    sequence: Annotated[str | None, typer.Option(help="KITTI sequence (NN).")] = None,
    frames: Annotated[str | None, typer.Option(help="Frame range A:B (Python slice).")] = None,
    k: Annotated[
        int | None,
        typer.Option(help="Map entries per query, closest by pose (default: the calibration's)."),
    ] = None,
    seed: Annotated[int | None, typer.Option(help="RANSAC seed (default: the job's).")] = None,
    camera: Annotated[str | None, typer.Option(help="TUM: freiburg1|2|3|default.")] = None,
    depth_from: Annotated[
        str | None, typer.Option(help="KITTI: keypoint depth from lidar (default) or stereo.")
    ] = None,
    condition: Annotated[
        str | None,
        typer.Option(
            "--condition",
            metavar="NAME",
            help="Calibrate this condition's model (an entry tag, e.g. night) from a run "
            "recorded in it; the map's base calibration (needed) is left untouched. "
            "Hypotheses from entries with the tag are weighed by it.",
        ),
    ] = None,
) -> None:
    """Fit the map's measurement model (mu1, Sigma1, mu2, Sigma2) on a training run and
    store it with its provenance (a recorded job; the run is not added to the map).
    With --condition NAME (e.g. a night run, --condition night) it becomes the model of
    the entries tagged NAME; calibrating the base again keeps it (same vocabulary)."""
    from monoloc.server.ingest.common import parse_frame_range
    from monoloc.server.ingest.manage import open_source
    from monoloc.server.ingest.report import progress_bar
    from monoloc.server.jobs.calibration import (
        CalibrationParams,
        describe_calibration,
        run_calibration_job,
    )

    params = job_params(
        CalibrationParams,
        format=fmt,
        path=str(run),
        sequence=sequence,
        frames=frames,
        depth_from=depth_from,
        k=k,
        seed=seed,
        condition=condition,
    )
    settings, factory = open_database(ctx)
    source = open_source(
        params.format,
        run,
        sequence=params.sequence,
        frames=parse_frame_range(params.frames),
        tum_camera=camera,
        depth_from=params.depth_from,
    )
    condition = params.condition
    with progress_bar(f"calibrating on {source.name}") as update:
        job, calibration = run_calibration_job(factory, map_ref, source, params, progress=update)
    if condition is None:
        typer.echo(f"job {job.id} {job.state}: map {job.map_id} calibrated")
    else:
        typer.echo(f"job {job.id} {job.state}: map {job.map_id} condition {condition} calibrated")
        calibration = calibration["conditions"][condition]
    for line in describe_calibration(calibration):
        typer.echo(line)
    _echo_fit(settings, factory, job.map_id, calibration)


@map_app.command("add-image")
def map_add_image(
    ctx: typer.Context,
    image: Annotated[Path, typer.Argument(help="PNG/JPEG reference image.")],
    map_ref: MapRef,
    pose: Annotated[
        str | None,
        typer.Option(help="T_world_from_cam (z-up world): 16 (or 12) numbers, row-major."),
    ] = None,
    pose_file: Annotated[Path | None, typer.Option(help="File with those numbers.")] = None,
    depth: Annotated[Path | None, typer.Option(help="Registered 16-bit depth PNG.")] = None,
    depth_scale: Annotated[float, typer.Option(help="Depth units per metre.")] = 5000.0,
    lidar: Annotated[Path | None, typer.Option(help="KITTI .bin LiDAR scan.")] = None,
    lidar_extrinsics: Annotated[
        str | None, typer.Option(help="T_cam_from_lidar: a calib.txt (Tr) or 12/16 numbers.")
    ] = None,
    tags: str = "",
) -> None:
    """Add one reference image with its pose and a depth image or a LiDAR scan."""
    from monoloc.server.ingest.common import read_bytes
    from monoloc.server.ingest.manage import find_map
    from monoloc.server.ingest.single import (
        add_single_image,
        depth_source_from_file,
        lidar_source_from_file,
        parse_numbers,
        read_lidar_extrinsics,
        read_pose_file,
        transform_from_numbers,
    )

    if (pose is None) == (pose_file is None):
        raise typer.BadParameter("give exactly one of --pose and --pose-file")
    if (depth is None) == (lidar is None):
        raise typer.BadParameter("give exactly one of --depth and --lidar")
    if lidar is not None and lidar_extrinsics is None:
        raise typer.BadParameter("--lidar needs --lidar-extrinsics")
    _, factory = open_database(ctx)
    T = (
        read_pose_file(pose_file)
        if pose_file
        else transform_from_numbers(parse_numbers(pose, "--pose"), "--pose")
    )
    source = (
        depth_source_from_file(depth, depth_scale)
        if depth is not None
        else lidar_source_from_file(lidar, read_lidar_extrinsics(lidar_extrinsics))
    )
    record = find_map(factory, map_ref)
    tag_list = tuple(t.strip() for t in tags.split(",") if t.strip())
    summary, created = add_single_image(
        factory, record.id, read_bytes(image, "image"), T, source, tags=tag_list
    )
    verb = "added" if created else "already in the map:"
    typer.echo(
        f"{verb} entry {summary.id} at x={summary.x_m:.2f} y={summary.y_m:.2f} "
        f"with {summary.n_points} 3D keypoints"
    )


@map_app.command("bulk-tile")
def map_bulk_tile(
    ctx: typer.Context,
    map_ref: Annotated[str, typer.Argument(help="Destination map (name or id), already created.")],
    source: Annotated[
        list[str], typer.Option("--from", help="Source map (ingested as usual); repeatable.")
    ],
    entries: Annotated[int, typer.Option(help="Entries the destination holds when done.")],
    seed: Annotated[int, typer.Option(help="Seed of the tiles' turns and perturbations.")] = 0,
    batch_rows: Annotated[int, typer.Option(help="Rows per transaction.")] = 10_000,
) -> None:
    """Fill a map with perturbed, turned geographic copies of source maps (to size a
    deployment before a city of that size is mapped; server/ingest/bulk.py)."""
    from monoloc.server.ingest.bulk import TileConfig, prepare_tiling, write_tiles
    from monoloc.server.ingest.report import progress_bar

    _, factory = open_database(ctx)
    config = TileConfig(entries=entries, seed=seed, batch_rows=batch_rows)
    plan = prepare_tiling(factory, map_ref, list(source), config)
    with progress_bar("tiling") as update:
        summary = write_tiles(factory, plan, progress=update)
    typer.echo(
        f"map {summary.map_id}: added {summary.entries_added} entries in {summary.seconds:.1f} s "
        f"({summary.entries_per_s:.0f}/s), {summary.entries_total} in {summary.tiles} tiles, "
        f"version {summary.version}"
    )


@map_app.command("import")
def map_import(
    ctx: typer.Context,
    path: Annotated[Path, typer.Argument(help="COLMAP sparse model folder or kapture folder.")],
    map_ref: Annotated[str, typer.Option("--map", "-m", help="Map name or id (created if new).")],
    fmt: Annotated[str, typer.Option("--format", help="colmap | kapture")] = "colmap",
    images: Annotated[
        Path | None,
        typer.Option(help="COLMAP: the folder of the model's images (default: its images/)."),
    ] = None,
    points: Annotated[
        str,
        typer.Option(
            help="orb: ORB features on the image take the model's 3D points by proximity "
            "to its 2D observations; model: the model's observations as they are."
        ),
    ] = "orb",
    up: Annotated[
        str | None,
        typer.Option(
            help="The model's up axis: z | -y | y | auto (default: monoloc.json beside the "
            "model, else -y for COLMAP, z for kapture)."
        ),
    ] = None,
    scale: Annotated[float, typer.Option(help="Metres per model unit.")] = 1.0,
    radius_px: Annotated[
        float, typer.Option(help="--points orb: the 2D observation search radius.")
    ] = 3.0,
    tags: Annotated[str, typer.Option(help="Comma-separated tags, e.g. night.")] = "",
    kind: Annotated[str, typer.Option(help="Run kind: map | offcenter | night | ...")] = "map",
    skip_bad_frames: Annotated[
        bool, typer.Option(help="Skip unreadable images (reported) instead of failing.")
    ] = False,
    workers: Annotated[int, typer.Option(help="Threads building entries.")] = 2,
) -> None:
    """Import a COLMAP sparse model (with its images) or a kapture dataset as mapping runs
    (one per camera); idempotent like any ingestion."""
    from monoloc.core.errors import InvalidInputError
    from monoloc.server.entry_builder import BuildConfig
    from monoloc.server.formats.maps import import_sources_into_map
    from monoloc.server.formats.model import Association, import_sources
    from monoloc.server.ingest.pipeline import IngestConfig
    from monoloc.server.ingest.report import print_ingest_summary, progress_bar

    if fmt == "colmap":
        from monoloc.server.formats.colmap import read_colmap_model

        if images is None and (path / "images").is_dir():
            images = path / "images"  # monoloc's own export keeps them there
        if images is None:
            raise typer.BadParameter("--format colmap needs --images DIR")
        model = read_colmap_model(path, images)
    elif fmt == "kapture":
        from monoloc.server.formats.kapture_io import read_kapture

        model = read_kapture(path)
    else:
        raise InvalidInputError(f"unknown import format {fmt!r}: colmap or kapture")
    build = BuildConfig()
    sources = import_sources(
        model,
        fmt=fmt,
        up=up,
        scale=scale,
        points=points,
        association=Association(radius_px=radius_px),
        orb=build.orb,
    )
    _, factory = open_database(ctx)
    config = IngestConfig(build=build, workers=workers, skip_bad_frames=skip_bad_frames)
    tag_list = tuple(t.strip() for t in tags.split(",") if t.strip())
    for note in model.notes:
        typer.echo(note)
    with progress_bar(f"importing {model.name}") as update:
        record, summaries, created = import_sources_into_map(
            factory, map_ref, sources, kind=kind, tags=tag_list, config=config, progress=update
        )
    if created:
        typer.echo(f"created map {record.name} (id {record.id}), camera {record.camera}")
    for summary in summaries:
        print_ingest_summary(summary)


@map_app.command("export")
def map_export(
    ctx: typer.Context,
    out: Annotated[Path, typer.Argument(help="Output folder (created).")],
    fmt: Annotated[str, typer.Option("--format", help="colmap | kapture")] = "colmap",
    map_ref: Annotated[
        str | None,
        typer.Option("--map", "-m", help="Map name or id (with --trajectory: its camera)."),
    ] = None,
    trajectory: Annotated[
        Path | None,
        typer.Option(
            help="kapture: write this driven trajectory (monoloc drive's TUM or KITTI file)."
        ),
    ] = None,
    times: Annotated[
        Path | None, typer.Option(help="KITTI trajectory: its times.txt (one per line).")
    ] = None,
) -> None:
    """Write a map as a COLMAP sparse model or a kapture dataset, or a driven trajectory
    as kapture (z-up world; monoloc.json beside it says so)."""
    from monoloc.core.errors import InvalidInputError

    if trajectory is not None:
        from monoloc.server.formats.trajectory import export_trajectory

        if fmt != "kapture":
            raise InvalidInputError("--trajectory is written as kapture: give --format kapture")
        camera = None
        if map_ref is not None:
            from monoloc.server.ingest.manage import find_map

            _, factory = open_database(ctx)
            camera = find_map(factory, map_ref).camera
        n = export_trajectory(trajectory, out, times=times, camera=camera)
        typer.echo(f"wrote {n} poses of {trajectory} as kapture to {out}")
        return
    if map_ref is None:
        raise typer.BadParameter("give --map (or --trajectory)")
    from monoloc.server.formats.maps import export_map

    _, factory = open_database(ctx)
    record, n = export_map(factory, map_ref, fmt, out)
    typer.echo(f"wrote map {record.name} ({n} entries, version {record.version}) as {fmt} to {out}")


def _echo_fit(settings, factory, map_id: int, calibration: dict) -> None:
    """Say how the calibration matches the map's own entries (``calibrate.calibration_fit``):
    a warning when its training run's VLAD distances do not fit this map's."""
    from monoloc.server.calibrate import calibration_fit, neighbour_vlad_distances
    from monoloc.server.map_registry import MapRegistry

    index = MapRegistry(factory, settings.index_dir).get(map_id).index
    fit = calibration_fit(
        dict(calibration.get("provenance") or {}),
        neighbour_vlad_distances(index.poses_world(), index.vlads_at),
    )
    if fit["fits"] is None:
        typer.echo("fit to this map: not known (no entries 2-6 m apart, or no training figure)")
    elif fit["fits"]:
        typer.echo(
            f"fit to this map: VLAD distances {fit['map']['mean']:.3f} vs the training run's "
            f"{fit['training']['mean']:.3f} ({fit['shift_in_training_std']:+.1f} spreads): fits"
        )
    else:
        typer.secho(f"warning: {fit['warning']}", err=True, fg=typer.colors.YELLOW)
