"""`monoloc drive`: replay a recorded run against a map server with the particle filter."""

from __future__ import annotations

import dataclasses
from pathlib import Path

import typer


def drive(
    run_dir: Path = typer.Argument(
        ...,
        help="KITTI sequence (or dataset root with --sequence), TUM RGB-D run folder, or a "
        "ROS 2 bag (folder or .mcap/.db3)",
    ),
    server: str = typer.Option("http://127.0.0.1:8000", help="map server base URL"),
    map_ref: str | None = typer.Option(None, "--map", help="map id or name (or --tiles)"),
    tiles: Path | None = typer.Option(
        None,
        help="a sharded map's tile table (JSON, monoloc.core.tiles): each frame goes to "
        "its tile's shard group (router or group URLs from the table; --server, --map unused)",
    ),
    key: str = typer.Option(..., envvar="MONOLOC_API_KEY", help="API key with scope localize"),
    sequence: str | None = typer.Option(None, help="sequence NN under a KITTI dataset root"),
    frames: str | None = typer.Option(None, help="frame range A:B (python slice semantics)"),
    realtime: bool = typer.Option(False, help="send frames at their recorded times"),
    no_prior: bool = typer.Option(False, "--no-prior", help="always search the whole map"),
    particles: int = typer.Option(1000, help="number of particles"),
    k: int | None = typer.Option(None, help="retrieved entries per frame (server default 10)"),
    seed: int = typer.Option(0, help="seed of the filter's random generator"),
    lever_arm_m: float | None = typer.Option(
        None,
        help="camera distance ahead of the speed reference point, m (default: the rig's "
        "mounting; replaces only its lever arm)",
    ),
    lever_arm_from: Path | None = typer.Option(
        None, help="fit the lever arm on this recorded run with poses (e.g. the training run)"
    ),
    mount_from: Path | None = typer.Option(
        None,
        help="fit where the camera sits (lever arm, lateral offset, yaw offset) on this "
        "recorded run with poses, taken by the same car; height, pitch and roll from the rig",
    ),
    out: Path = typer.Option(Path("out/drive"), help="prefix of the trajectory files"),
    topic: list[str] | None = typer.Option(
        None,
        help="ROS bag: ROLE=TOPIC (roles image, camera_info, odometry, truth), repeatable; "
        "image and odometry are found by type when the bag has one of each",
    ),
    bag_out: Path | None = typer.Option(
        None,
        help="also write the track as a new ROS 2 bag folder (nav_msgs/Odometry on "
        "/monoloc/odometry; needs the formats extra)",
    ),
    bag_storage: str = typer.Option("sqlite3", help="storage of --bag-out: sqlite3 or mcap"),
    camera: Path | None = typer.Option(
        None,
        help="the camera that took the frames, when the run does not say: a camera.yaml "
        "(ROS's calibration layout), a camera.json (fx, fy, cx, cy, width, height, "
        "distortion_model, D) or a KITTI calib.txt (P0)",
    ),
    image_format: str = typer.Option(
        "recorded",
        help="how frames are sent: recorded (the files' own PNG/JPEG bytes) or jpeg "
        "(re-encoded on the vehicle with Pillow: fewer bytes, less server decode time)",
    ),
    jpeg_quality: int = typer.Option(90, help="quality of --image-format jpeg (1-95)"),
) -> None:
    """Stream a run's frames, run the filter, write TUM + KITTI trajectories, print metrics."""
    from rich.console import Console
    from rich.progress import Progress

    from monoloc.client.api import MonolocClient
    from monoloc.client.bag_replay import is_bag, read_bag_run
    from monoloc.client.drive import (
        DriveConfig,
        write_bag,
        write_geojson,
        write_outputs,
        write_vehicle_track,
    )
    from monoloc.client.drive import drive as run_drive
    from monoloc.client.motion import MotionConfig, fit_lever_arm_m
    from monoloc.client.particle_filter import FilterConfig
    from monoloc.client.replay import mounting_note, parse_frames, read_run
    from monoloc.client.report import metrics_table
    from monoloc.client.transcode import with_image_format
    from monoloc.core.errors import InvalidInputError, MonolocError
    from monoloc.core.mounting import CameraMounting

    console = Console(stderr=True)
    if (map_ref is None) == (tiles is None):
        raise typer.BadParameter("give --map or --tiles (a sharded map), one of them")
    if tiles is not None and realtime:
        raise typer.BadParameter("a sharded drive sends frames in turn", param_hint="--realtime")
    table = None
    if tiles is not None:  # a wrong table is refused before the run is read
        from monoloc.core.tiles import read_tile_table

        table = read_tile_table(tiles)
    if bag_out is not None:  # refused before the drive, not after it
        _check_bag_out(bag_out, bag_storage)
    if is_bag(run_dir):
        run = read_bag_run(run_dir, _topics(topic)).select(parse_frames(frames))
    else:
        run = read_run(run_dir, sequence).select(parse_frames(frames))
    run = with_image_format(run, image_format, jpeg_quality)
    if camera is not None:
        intrinsics, mounting = _camera_file(camera, run)
        run = run.with_intrinsics(intrinsics)
        if mounting is not None:
            run = run.with_mounting(mounting, mounting_note(mounting, str(camera)))
    for note in run.notes:
        console.print(f"[yellow]note:[/] {note}")
    if mount_from is not None:
        run = _fitted_mounting(mount_from, run)
        console.print(f"[yellow]note:[/] {run.notes[-1]}")
    if lever_arm_m is None and lever_arm_from is not None:
        fit_run = read_run(lever_arm_from)
        if fit_run.truth_world is None:
            raise InvalidInputError(f"{lever_arm_from} has no poses to fit a lever arm on")
        lever_arm_m = fit_lever_arm_m(
            fit_run.truth_world, fit_run.timestamps_s, fit_run.signals[:, 0]
        )
        console.print(f"[yellow]note:[/] lever arm {lever_arm_m:.3f} m fitted on {fit_run.name}")
    if lever_arm_m is not None:  # the shorthand: the rig's mounting with this lever arm
        mounting = dataclasses.replace(run.mounting or CameraMounting(), lever_arm_m=lever_arm_m)
        run = run.with_mounting(mounting)
    elif run.mounting is None and run.lever_arm_m is None:
        console.print(
            "[yellow]note:[/] camera mounting unknown, the camera taken for the speed "
            "reference: a camera ahead of it then falls to the outside of turns "
            "(--mount-from, --lever-arm-m or --lever-arm-from)"
        )
    motion = MotionConfig(mounting=run.mounting, lever_arm_m=run.lever_arm_m or 0.0)
    config = DriveConfig(
        filter=FilterConfig(n_particles=particles, motion=motion),
        k=k,
        realtime=realtime,
        use_prior=not no_prior,
        seed=seed,
    )
    if table is not None:
        result = _sharded_drive(table, key, run, config, console)
    else:
        with MonolocClient(server, key) as client:
            map_id = client.find_map_id(map_ref)
            model, calibrated = client.measurement_model(map_id)
            if not calibrated:
                console.print("[yellow]note:[/] map not calibrated: default measurement model")
            with Progress(console=console) as bar:
                task = bar.add_task(f"driving {run.name}", total=len(run))
                result = run_drive(
                    client,
                    map_id,
                    run,
                    model,
                    config,
                    progress=lambda i, n: bar.update(task, completed=i),
                )
    for note in result.notes[len(run.notes) :]:
        console.print(f"[yellow]note:[/] {note}")
    if result.all_refused:
        first = min(result.errors)
        raise MonolocError(
            f"the server refused every one of the {len(run)} frames; frame {first}: "
            f"{result.errors[first]}"
        )
    tum, kitti = write_outputs(result, out)
    vehicle = write_vehicle_track(result, out)
    geojson = write_geojson(result, out)
    bag_path = write_bag(result, bag_out, bag_storage) if bag_out is not None else None
    Console().print(metrics_table(result))
    written = [tum, kitti, *(p for p in (vehicle, geojson, bag_path) if p is not None)]
    console.print("trajectories: " + ", ".join(str(p) for p in written))
    if result.geo_reference is None:
        console.print(f"no GeoJSON track: map {map_ref or tiles} has no geographic reference")
    elif geojson is None:
        console.print("no GeoJSON track: the filter gave no estimate")


def _sharded_drive(table, key: str, run, config, console):
    """The drive of ``run`` over the shard groups of the tile table ``table``."""
    from rich.progress import Progress

    from monoloc.client.drive import drive_with
    from monoloc.client.sharded import ShardedLocalizer
    from monoloc.core.errors import InvalidInputError

    if run.intrinsics is None:
        raise InvalidInputError(f"{run.name}: the camera that took the frames is unknown")
    with ShardedLocalizer.connect(table, key, run.intrinsics) as localizer:
        model, calibrated = localizer.measurement_model()
        if not calibrated:
            console.print("[yellow]note:[/] map not calibrated: default measurement model")
        with Progress(console=console) as bar:
            groups = len(table.groups)
            task = bar.add_task(f"driving {run.name} over {groups} groups", total=len(run))
            result = drive_with(
                localizer,
                run,
                model,
                config,
                localizer.geo_reference(),
                progress=lambda i, n: bar.update(task, completed=i),
            )
        for name, counts in localizer.counts.items():
            console.print(
                f"shard group {name}: " + ", ".join(f"{k} {v}" for k, v in counts.items())
            )
        for error in localizer.last_errors.values():
            console.print(f"[yellow]note:[/] last failure of shard group {error}")
        console.print(
            f"frames to one group {localizer.routes['one_group']}, "
            f"to several {localizer.routes['several_groups']}"
        )
    return result


def _fitted_mounting(path: Path, run):
    """``run`` with the camera's planar mounting fitted on the recorded run ``path`` (its
    poses and measured speed; ``fit_mount``) and the rest of the mounting (height,
    pitch, roll) from the run's own rig, else ``path``'s."""
    from monoloc.client.motion import fit_mount
    from monoloc.client.replay import mounting_note, read_run
    from monoloc.core.errors import InvalidInputError
    from monoloc.core.mounting import CameraMounting

    fit_run = read_run(path)
    if fit_run.truth_world is None:
        raise InvalidInputError(f"{path} has no poses to fit a camera mounting on")
    planar = fit_mount(fit_run.truth_world, fit_run.timestamps_s, fit_run.signals[:, 0])
    rig = run.mounting or fit_run.mounting or CameraMounting()
    mounting = dataclasses.replace(
        rig, lever_arm_m=planar.x_m, lateral_m=planar.y_m, yaw_rad=planar.yaw_rad
    )
    return run.with_mounting(mounting, mounting_note(mounting, f"fitted on {fit_run.name}"))


def _check_bag_out(path: Path, storage: str) -> None:
    """A usage error unless ``path`` is free, ``storage`` known and rosbags installed."""
    if storage not in ("sqlite3", "mcap"):
        raise typer.BadParameter(f"sqlite3 or mcap, got {storage!r}", param_hint="--bag-storage")
    if path.exists():
        raise typer.BadParameter(
            f"{path} already exists (a bag is written to a new folder)", param_hint="--bag-out"
        )
    try:
        import rosbags.rosbag2  # noqa: F401
    except ModuleNotFoundError:
        raise typer.BadParameter(
            "writing a bag needs rosbags: pip install 'monoloc[bags]'", param_hint="--bag-out"
        ) from None


def _topics(items: list[str] | None) -> dict[str, str]:
    """The ``--topic ROLE=TOPIC`` values as a dict (a usage error otherwise)."""
    from monoloc.core.formats.rosbag import parse_topic_options

    try:
        return parse_topic_options(items)
    except ValueError as exc:
        raise typer.BadParameter(str(exc)) from None


def _camera_file(path: Path, run):
    """(intrinsics, mounting or None) of a camera.yaml (ROS's calibration layout), a
    camera.json (its size, else the run's first image's) or a KITTI calib.txt (P0, with
    the run's first image's size)."""
    import json

    from monoloc.core.camera import CameraIntrinsics, LensDistortion
    from monoloc.core.errors import InputFileError, InvalidInputError
    from monoloc.core.formats import kitti
    from monoloc.core.formats.camera_yaml import read_camera_yaml
    from monoloc.core.formats.png import png_size
    from monoloc.core.mounting import CameraMounting

    if path.suffix.lower() in (".yaml", ".yml"):
        found = read_camera_yaml(path)
        return found.intrinsics, found.mounting

    def first_image_size() -> tuple[int, int]:
        if not len(run) or run.read_image is not None:
            raise InputFileError(
                path, "give the camera's width and height (the run's frames are no files)"
            )
        return png_size(run.image_paths[0])

    if path.suffix.lower() == ".json":
        try:
            data = json.loads(path.read_text())
            fx, fy, cx, cy = (float(data[k]) for k in ("fx", "fy", "cx", "cy"))
        except (OSError, ValueError, KeyError, TypeError) as exc:
            raise InputFileError(
                path, f"needs a JSON object with numeric fx, fy, cx, cy ({exc})"
            ) from exc
        width, height = (
            data.get("width_px", data.get("width")),
            data.get("height_px", data.get("height")),
        )
        if width is None or height is None:
            width, height = first_image_size()
        try:
            lens = LensDistortion.parse(
                data.get("distortion_model"), data.get("D", data.get("distortion"))
            )
        except (TypeError, ValueError) as exc:
            raise InputFileError(path, f"bad distortion_model / D ({exc})") from exc
        mounting = None
        try:
            if data.get("T_vehicle_from_cam") is not None:
                mounting = CameraMounting.from_dict(
                    {"T_vehicle_from_cam": data["T_vehicle_from_cam"]}
                )
            elif data.get("mounting") is not None:
                mounting = CameraMounting.from_dict(data["mounting"])
        except InvalidInputError as exc:
            raise InputFileError(path, str(exc)) from exc
        return CameraIntrinsics(fx, fy, cx, cy, int(width), int(height), lens), mounting
    return kitti.read_calib_file(path).intrinsics(*first_image_size()), None
