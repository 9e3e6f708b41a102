"""The steps of `monoloc demo` (see monoloc/demo/__init__.py), each printing its progress."""

from __future__ import annotations

import json
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from rich.console import Console
from rich.progress import BarColumn, Progress, TextColumn, TimeElapsedColumn

from monoloc import local_server
from monoloc.client.api import MonolocClient
from monoloc.client.drive import DriveConfig, DriveResult, drive, write_outputs
from monoloc.client.replay import read_run

RUNS = ("train", "map", "query", "night", "nightmap")


@dataclass
class Dataset:
    root: Path
    sequences: dict[str, str]  # run kind -> sequence id
    camera: dict


def _progress(console: Console) -> Progress:
    return Progress(
        TextColumn("  {task.description}"),
        BarColumn(),
        TextColumn("{task.percentage:>3.0f}%"),
        TimeElapsedColumn(),
        console=console,
    )


class DemoSteps:
    def __init__(self, config, console: Console) -> None:
        self.config = config
        self.console = console
        self.out = config.out_dir

    # ---- 1 ---------------------------------------------------------------------------
    def generate(self) -> Dataset:
        from monoloc.sim.generate import GenerateConfig, generate_dataset

        root = self.out / f"city_{self.config.size}_{self.config.frames}_s{self.config.seed}"
        meta_path = root / "dataset.json"
        if meta_path.exists():
            self.console.print(f"[bold]1[/] reusing the sim city in {root}")
        else:
            self.console.print(
                f"[bold]1[/] generating a {self.config.size} sim city: runs "
                f"{', '.join(RUNS)}, {self.config.frames} frames each"
            )
            gen = GenerateConfig(
                size=self.config.size,
                seed=self.config.seed,
                runs=RUNS,
                max_frames=self.config.frames,
                workers=2,
            )
            with _progress(self.console) as bar:
                tasks: dict[str, int] = {}

                def progress(seq: str, done: int, total: int) -> None:
                    if seq not in tasks:
                        tasks[seq] = bar.add_task(f"sequence {seq}", total=total)
                    bar.update(tasks[seq], completed=done)

                generate_dataset(gen, root, progress)
        meta = json.loads(meta_path.read_text())
        sequences = {s["run"]: s["id"] for s in meta["sequences"]}
        return Dataset(root, sequences, meta.get("camera", {}))

    # ---- 3 ---------------------------------------------------------------------------
    def _upload(self, client, map_id, dataset, run, path, label, **fields) -> dict:
        seq = dataset.sequences[run]
        archive = local_server.kitti_archive(dataset.root, seq, self.out / f"upload_{run}.tar")
        try:
            answer = local_server.upload_run(client, map_id, archive, path, sequence=seq, **fields)
        finally:
            archive.unlink(missing_ok=True)
        job_id = answer["job"]["id"] if "job" in answer else answer["id"]
        with _progress(self.console) as bar:
            task = bar.add_task(label, total=1.0)
            job = local_server.wait_job(client, job_id, lambda p: bar.update(task, completed=p))
        return job

    def build_map(self, client: MonolocClient, dataset: Dataset) -> int:
        from monoloc.core.formats.kitti import read_calib_file
        from monoloc.core.formats.png import png_size

        seq_dir = dataset.root / "sequences" / dataset.sequences["map"]
        fx, fy, cx, cy = read_calib_file(seq_dir / "calib.txt").pinhole
        width, height = png_size(seq_dir / "image_0" / "000000.png")
        camera = dict(fx=fx, fy=fy, cx=cx, cy=cy, width_px=width, height_px=height)
        stamp = time.strftime("%Y%m%d-%H%M%S")
        self.console.print("[bold]3[/] training the vocabulary on the train run")
        scratch = client.request(
            "POST", "/v1/maps", json={"name": f"demo-vocab-{stamp}", "camera": camera}
        ).json()
        self._upload(
            client,
            scratch["id"],
            dataset,
            "train",
            "/v1/maps/{map_id}/runs",
            "train run: vocabulary + ingestion",
            kind="map",
            train_vocabulary="true",
        )
        vocab_hash = client.request("GET", f"/v1/maps/{scratch['id']}").json()["vocabulary"]["hash"]
        client.request("DELETE", f"/v1/maps/{scratch['id']}")
        the_map = client.request(
            "POST",
            "/v1/maps",
            json={"name": f"demo-{stamp}", "camera": camera, "vocabulary": vocab_hash},
        ).json()
        map_id = the_map["id"]
        self.console.print(f"    map {map_id} uses vocabulary {vocab_hash}; calibrating")
        self._upload(
            client,
            map_id,
            dataset,
            "train",
            "/v1/maps/{map_id}/calibration/jobs",
            "train run: measurement-model calibration",
        )
        self.console.print("    uploading the map run")
        self._upload(
            client,
            map_id,
            dataset,
            "map",
            "/v1/maps/{map_id}/runs",
            "map run: ingestion",
            kind="map",
        )
        info = client.request("GET", f"/v1/maps/{map_id}").json()
        self.console.print(
            f"    map {map_id}: {info.get('n_entries')} entries, version {info.get('version')}"
        )
        return map_id

    # ---- 4 ---------------------------------------------------------------------------
    def _drive(self, client, map_id, dataset, run, label) -> DriveResult:
        replay = read_run(dataset.root, dataset.sequences[run])
        model, calibrated = client.measurement_model(map_id)
        with _progress(self.console) as bar:
            task = bar.add_task(label, total=len(replay))
            result = drive(
                client,
                map_id,
                replay,
                model,
                DriveConfig(),
                progress=lambda i, n: bar.update(task, completed=i),
            )
        write_outputs(result, self.out / "trajectories" / label.replace(" ", "_"))
        if not calibrated:
            result.notes.append("map not calibrated: default measurement model")
        return result

    def add_night_entries(self, client, map_id, dataset) -> int:
        from monoloc.server.ingest.sources import read_kitti_sequence

        seq = read_kitti_sequence(dataset.root, dataset.sequences["nightmap"])
        added = 0
        with _progress(self.console) as bar:
            task = bar.add_task("operator adds night images", total=seq.n_frames)
            for i, frame in enumerate(seq.frames):
                try:
                    answer = local_server.add_entry(
                        client,
                        map_id,
                        frame.image_path,
                        frame.scan_path,
                        frame.T_world_from_cam,
                        seq.T_cam_from_lidar,
                        "night",
                        frame.timestamp_s,
                    )
                    added += int(bool(answer.get("created", True)))
                except local_server.MonolocError:
                    pass  # an image with too few 3D points is refused; the operator moves on
                bar.update(task, completed=i + 1)
        return added

    def drive_all(self, client, map_id, dataset) -> dict[str, DriveResult]:
        self.console.print("[bold]4[/] driving the query run over the WebSocket")
        results = {"query": self._drive(client, map_id, dataset, "query", "query run")}
        self.console.print("    the night run against the day map")
        results["night, day map"] = self._drive(client, map_id, dataset, "night", "night before")
        added = self.add_night_entries(client, map_id, dataset)
        self.console.print(f"    {added} night images added; the night run again")
        results[f"night, +{added} night images"] = self._drive(
            client, map_id, dataset, "night", "night after"
        )
        return results

    # ---- 4b --------------------------------------------------------------------------
    def closed_loop_lap(self, client) -> dict:
        """A short closed-loop drive on the indoor track: a part-lap centre-line map
        recorded by the sim's vehicle, then the 1:10 car steering on monoloc's estimate."""
        from monoloc.sim.closed_loop_plots import plot_cases
        from monoloc.sim.closed_loop_study import StudyConfig, run_study
        from monoloc.sim.closed_loop_world import IndoorLoopWorld

        started = time.monotonic()
        self.console.print("[bold]4b[/] closed loop: the 1:10 car steers on monoloc's estimate")
        world = IndoorLoopWorld("small", self.config.seed)
        study = StudyConfig(
            laps=1.0,
            map_laps=0.7,
            train_laps=0,
            max_frames=self.config.closed_loop_frames,
            cases=("closed",),
        )
        out = self.out / "closed_loop"
        summary = run_study(client, world, study, out, log=lambda t: self.console.print(f"  {t}"))
        results = summary.pop("_results")
        plots = plot_cases(results, self.out, prefix="closed_loop")
        m = summary["cases"]["closed"]
        self.console.print(
            f"    {m['frames']} frames: localization RMSE {100 * m['loc_rmse_m']:.1f} cm, "
            f"lateral tracking error max {100 * m['lateral_max_m']:.1f} cm "
            f"(lane half width {100 * m['lane_half_width_m']:.0f} cm), "
            f"{m['lane_departures']} lane departures"
        )
        return {
            "metrics": m,
            "plots": [str(p) for p in plots],
            "seconds": time.monotonic() - started,
        }

    # ---- 5 and 6 -----------------------------------------------------------------------
    def report(self, client, map_id, dataset, results, total_s: float) -> dict:
        from monoloc.demo.report import make_plots, summary_table

        self.console.print(summary_table(results))
        plots = make_plots(self.out, client, map_id, dataset, results)
        return {
            "map_id": map_id,
            "runs": {name: summary_dict(r) for name, r in results.items()},
            "paper": {"kitti00_position_rmse_m": 0.313, "rate_hz": 10},
            "plots": [str(p) for p in plots],
            "total_s": total_s,
        }


def summary_dict(result: DriveResult) -> dict:
    m = result.metrics.to_dict() if result.metrics else {}
    stages: dict[str, dict[str, float]] = {}
    for name in sorted({k for t in result.server_timings_ms for k in t}):
        values = [t[name] for t in result.server_timings_ms if name in t]
        stages[name] = {
            "p50": float(np.percentile(values, 50)),
            "p99": float(np.percentile(values, 99)),
        }
    lat = result.latency_ms[np.isfinite(result.latency_ms)]
    return {
        "metrics": m,
        "frames_per_s": result.frames_per_s,
        "server_stages_ms": stages,
        "round_trip_ms": {
            "p50": float(np.percentile(lat, 50)),
            "p99": float(np.percentile(lat, 99)),
        }
        if len(lat)
        else {},
        "dropped": int(result.dropped.sum()),
        "notes": result.notes,
    }
