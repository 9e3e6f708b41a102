"""Gather bench/results/*.json into bench/REPORT.md with plots (bench/results/plots/),
and the README's one results table between its ``<!-- results:begin -->`` and
``<!-- results:end -->`` markers.

Every number in the report is read from a result file written by a bench script in the
same `make bench` run; a missing file is reported as "not run", never filled in. Run from
the repository root: ``python -m bench.report``.
"""

from __future__ import annotations

import json
import os
import platform
import subprocess
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from monoloc.client.trajectory import ExcursionCauses

HERE = Path(__file__).parent
RESULTS = HERE / "results"
PLOTS = RESULTS / "plots"
README = HERE.parent / "README.md"
RESULTS_BEGIN = "<!-- results:begin -->"
RESULTS_END = "<!-- results:end -->"


def load(name: str, results: Path = RESULTS) -> dict | None:
    path = results / f"{name}.json"
    return json.loads(path.read_text()) if path.exists() else None


def table(header: list[str], rows: list[list]) -> str:
    def cell(v):
        if isinstance(v, float):
            return f"{v:.3g}" if abs(v) < 1000 else f"{v:.0f}"
        return "-" if v is None else str(v)

    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(cell(v) for v in row) + " |" for row in rows]
    return "\n".join(lines)


def verdict(value, goal, lower_is_better=True) -> str:
    if value is None:
        return "not run"
    ok = value <= goal if lower_is_better else value >= goal
    return "met" if ok else "**missed**"


def accuracy_section(name: str, data: dict | None) -> list[str]:
    if data is None:
        return [f"## Accuracy ({name})", "", "not run", ""]
    out = [f"## Accuracy ({name})", ""]
    rows = []
    for variant, m in {**data.get("query", {}), **data.get("night", {})}.items():
        rows.append(
            [
                variant,
                m["coverage"],
                m["position_rmse_m"],
                m["position_median_m"],
                m["heading_rmse_deg"],
                m["within_0_25m_2deg"],
                m["within_0_5m_5deg"],
                m["within_5m_10deg"],
            ]
        )
    out.append(
        table(
            [
                "variant",
                "frames with estimate",
                "RMSE m",
                "median m",
                "heading deg",
                "<0.25 m/2°",
                "<0.5 m/5°",
                "<5 m/10°",
            ],
            rows,
        )
    )
    met = data.get("goals_met")
    if met:
        # written by bench/accuracy.py (issue 13 item 5): each goal and whether it was met
        seed = data.get("seed", "?")
        floors = data.get("goals_floor") or {}

        def verdict(name: str, ok: bool) -> str:
            if ok:
                return "met"
            floor = floors.get(name)
            return "NOT met" if floor is None else f"NOT met (a pose exact to the map: {floor:.3f})"

        verdicts = "; ".join(f"{k}: {verdict(k, v)}" for k, v in met.items())
        out += ["", f"Goals (city seed {seed}): {verdicts}."]
    seeds = data.get("filter_seeds")
    if seeds:
        day, night = seeds["day_rmse_m"], seeds["night_rmse_m"]
        out += [
            "",
            f"Filter seeds 0-{len(day) - 1} (the RANSAC draws follow them): day RMSE "
            + " / ".join(f"{v:.3f}" for v in day)
            + " m, night with night entries "
            + " / ".join(f"{v:.3f}" for v in night)
            + f" m; night / day of the means {sum(night) / sum(day):.2f}x.",
        ]
    floor = data.get("floor", {}).get("query", {}).get("full")
    if floor:
        out += [
            "",
            f"Error floor (same city, recording errors off): RMSE "
            f"{floor['position_rmse_m']:.3f} m, median {floor['position_median_m']:.3f} m, "
            f"heading RMSE {floor['heading_rmse_deg']:.2f} deg.",
        ]
    floors = (
        ("recording_floor", "query"),
        ("recording_floor_pnp", "query, PnP covariance model"),  # results before 2026-11-28
        ("recording_floor_mode", "query, the particles' mode (no refinement)"),
        ("recording_floor_paper", "query, paper model"),
        ("night_recording_floor", "night + night entries; approximate: two maps"),
    )
    for key, what in floors:
        rf = data.get(key)
        if rf:
            extra = ""
            if "exact_over_best_of_k" in rf:  # results written since 2026-11-27, late morning
                extra = (
                    f" (filter / best of k {rf['exact_over_best_of_k']:.2f}); the run's written "
                    f"truth alone is off its true poses by median "
                    f"{rf['query_alone']['median_m']:.3f} m, RMSE "
                    f"{rf['query_alone']['rmse_m']:.3f} m"
                )
            out += [
                "",
                f"Recording errors' floor ({what}): a pose exact relative to the map scores "
                f"median {rf['floor']['median_m']:.3f} m, RMSE {rf['floor']['rmse_m']:.3f} m "
                f"against the written truth{extra}; judged against the map's own frame the "
                "filter has "
                f"median {rf['filter_vs_map_frame']['median_m']:.3f} m, RMSE "
                f"{rf['filter_vs_map_frame']['rmse_m']:.3f} m, best of k median "
                f"{rf['best_of_k_vs_map_frame_median_m']:.3f} m"
                + (
                    ", the likeliest hypothesis median "
                    f"{rf['likeliest_vs_map_frame_median_m']:.3f} m."
                    if "likeliest_vs_map_frame_median_m" in rf
                    else "."
                ),
            ]
            if "best_of_k_blurred" in rf:  # results written since 2026-11-29 evening
                out[-1] += (
                    f" Best of k against the written truth: median "
                    f"{rf['best_of_k_written_median_m']:.3f} m; with every hypothesis blurred "
                    "by random noise "
                    + ", ".join(
                        f"{float(s) * 100:.0f} cm: {m:.3f} m"
                        for s, m in rf["best_of_k_blurred"].items()
                    )
                    + " (lower: the oracle gains from spread alone)."
                )
    for run, causes in data.get("excursions", {}).items():
        out += ["", f"Frames off ({run}): {ExcursionCauses(**causes).text()}."]
    reg = data.get("night_registration")
    if reg:
        mean_x, mean_y = reg["offset_mean_m"]
        registered = data.get("night", {}).get("night, + night entries registered to the map")
        day = data.get("query", {}).get("full", {}).get("position_rmse_m")
        ratio = (
            f"{registered['position_rmse_m'] / day:.2f}x" if registered and day else "not measured"
        )
        out += [
            "",
            f"Night run registered to the day map (monoloc map ingest --register): "
            f"{reg['frames_used']} of {reg['frames_measured']} localized night frames used "
            f"(noise {reg['noise_m'][0]:.3f} / {reg['noise_m'][1]:.3f} m per frame); moved by "
            f"x {mean_x:+.3f} m, y {mean_y:+.3f} m on average (a run with fewer than 20 frames "
            "used is left where it is). Night / day RMSE with the registered night run: "
            f"{ratio}.",
        ]
    prov = data.get("calibration", {}).get("provenance")
    if prov:
        out += ["", f"Calibration: {json.dumps(prov)}"]
    if data.get("stereo"):
        out += ["", *stereo_lines(data["stereo"])]
    return out + [""]


def stereo_lines(data: dict) -> list[str]:
    """The stereo-built map beside the LiDAR-built one (bench/stereo.py's figures)."""
    d, lid, ste = data["depth"], data["lidar"], data["stereo"]
    rows = []
    for source, r in (("lidar", lid), ("stereo", ste)):
        full = r["query"]["full"]
        rows.append(
            [
                source,
                d[source]["keypoints_with_depth"],
                d[source]["rel_error_median"],
                d[source]["share_error_over_10pct"],
                r["entries"],
                full["position_rmse_m"],
                full["position_median_m"],
                full["heading_rmse_deg"],
            ]
        )
    header = ["depth from", "keypoints with depth", "depth error median", "error > 10 %"]
    header += ["entries", "query RMSE m", "median m", "heading deg"]
    return ["Maps from a stereo camera (same runs, bench/stereo.py):", "", table(header, rows)]


def plot_accuracy(data: dict | None, name: str) -> str | None:
    if not data:
        return None
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    variants = {**data.get("query", {}), **data.get("night", {})}
    names = list(variants)
    rmse = [variants[v]["position_rmse_m"] or 0.0 for v in names]
    fig, ax = plt.subplots(figsize=(8, 3.5))
    ax.barh(names, rmse, color="tab:blue")
    ax.axvline(0.15, color="green", ls="--", label="goal 0.15 m")
    ax.axvline(0.313, color="red", ls=":", label="paper KITTI 00")
    ax.set_xscale("log")
    ax.set_xlabel("position RMSE (m), frames with an estimate")
    ax.legend(fontsize=8)
    fig.tight_layout()
    PLOTS.mkdir(parents=True, exist_ok=True)
    path = PLOTS / f"accuracy_{name}.png"
    fig.savefig(path, dpi=100)
    plt.close(fig)
    return str(path.relative_to(HERE))


def crash_section(data: dict | None) -> list[str]:
    """SIGKILL trials (bench/crash.py): failures by kind of check, restart times."""
    lines = ["", "## Crash trials: SIGKILL of the server process (bench/crash.py)", ""]
    if not data:
        return lines + ["not run"]
    rows = [[name, n, "met" if n == 0 else "**missed**"] for name, n in data["failures"].items()]
    lines.append(table(["trials with ...", "count", "goal 0"], rows))
    restart = data["restart_after_sigkill_s"]
    lines += [
        "",
        f"{data['trials']} trials ({data['by_kind']}), {data['acknowledged_writes']} "
        f"acknowledged writes checked; ingestion kills by job state at the kill: "
        f"{data['ingest_kills_by_job_state']}. Restart after SIGKILL p50 "
        f"{restart['p50']:.1f} s (max {restart['max']:.1f} s) vs a fresh start "
        f"{data['baseline_fresh_start_s']:.1f} s (baseline, same run).",
    ]
    return lines


def hostile_section(data: dict | None) -> list[str]:
    """Decoding cost of a compression bomb (bench/hostile.py)."""
    lines = ["", "## A compression bomb against the decoder (bench/hostile.py)", ""]
    if not data:
        return lines + ["not run"]
    rows = [[name, f"{ms:.1f}", data["outcome"][name]] for name, ms in data["cpu_ms"].items()]
    lines.append(table(["image, path", "CPU ms", "outcome"], rows))
    lines += [
        "",
        f"The bomb: {data['bomb_bytes'] / 1e6:.1f} MB declaring the camera's size, inflating "
        f"to {data['inflate_mb']} MB; the real frame {data['real_bytes'] / 1e3:.0f} kB.",
    ]
    return lines


def http_overhead_section(data: dict | None) -> list[str]:
    """Server CPU per request by HTTP implementation (bench/http_overhead.py)."""
    lines = ["", "## The HTTP layer's cost per request (bench/http_overhead.py)", ""]
    if not data:
        return lines + ["not run"]
    configs = list(data["results"])
    cases = list(data["results"][configs[0]])
    rows = []
    for case in cases:
        base = data["results"][configs[0]][case]["server_cpu_us_per_request_median"]
        for name in configs:
            us = data["results"][name][case]["server_cpu_us_per_request_median"]
            rows.append([case, name, f"{us:.0f}", f"{us / base:.2f}x"])
    lines.append(table(["request", "server", "server CPU us / request", "vs baseline"], rows))
    lines += [
        "",
        f"Median of {data['repeat']} alternating runs of {data['requests']} requests each; "
        "the baseline (first row of each request) is uvicorn's pure-Python fallback.",
    ]
    return lines


def formats_section(formats: dict | None, geopose: dict | None) -> list[str]:
    """Maps from COLMAP models vs LiDAR (bench/formats.py) and the GeoPose cost
    (bench/geopose.py)."""
    lines = ["", "## Maps from other formats (bench/formats.py, bench/geopose.py)", ""]
    if formats:
        d = formats["dataset"]
        rows = [
            [
                name,
                m["entries"],
                f"{m['points_per_entry']:.0f}",
                f"{100 * m['with_hypothesis']:.0f} %",
                f"{m['position_rmse_m']:.3f}" if m.get("position_rmse_m") is not None else "-",
                f"{m['position_median_m']:.3f}" if m.get("position_median_m") is not None else "-",
            ]
            for name, m in formats["maps"].items()
        ]
        header = ["map", "entries", "3D points / entry", "frames with a hypothesis"]
        lines.append(table(header + ["RMSE m", "median m"], rows))
        lines += [
            "",
            f"Sim city {d['size']}, seed {d['seed']}, {d['frames']} frames; the LiDAR-built map "
            "is the baseline, same query run.",
        ]
    else:
        lines.append("formats: not run")
    if geopose:
        lines += [
            "",
            f"GeoPose answers: a localize answer of {geopose['hypotheses']} hypotheses costs "
            f"{geopose['answer_with_geopose_us_p50']:.0f} us with GeoPoses vs "
            f"{geopose['answer_plain_us_p50']:.0f} us without (p50, same run).",
        ]
    return lines


def _cores(phase: dict) -> str:
    c = phase.get("cpu_cores")
    if c is None:
        return "-"
    return f"{c['load_generator']:.2f} / {c['server']:.2f} / {c['other']:.2f}"


def _held(run: dict) -> str:
    return f" ({run['held_by_vehicle']} held)" if run.get("held_by_vehicle") else ""


def fleet_section(data: dict | None, footprint: dict | None) -> list[str]:
    """bench/load.py (capacity, then 2x open loop) and bench/footprint.py."""
    out = ["## Fleet load: capacity, then twice capacity offered (bench/load.py)", ""]
    if data is None:
        out += ["not run", ""]
    else:
        g = data["goals"]
        out += [
            f"Goals at 2x: served >= {100 * g['served_share_min']:.0f} % of capacity, p99 <= "
            f"{g['p99_over_capacity_p50_max']:.0f}x the p50 at capacity, memory <= idle + "
            f"{g['memory_growth_mb_max']:.0f} MB, writes p99 <= {g['writes_p99_s_max']:.0f} s, "
            f"no 5xx but 503 (shed). {data['duration_s']:.0f} s per phase; the load generator "
            "shares the 2 cores with the server. *cores*: CPU used during the phase by the "
            "load generator / the replicas / every other process on the machine (other "
            "jobs), in cores; *per core*: frames served per core the replicas used, at 2x "
            "over at capacity (near 100 %: the replicas waste no CPU under overload, and a "
            "lower served share is CPU they did not get). *http-honours*: the vehicles "
            "do what monoloc's client library does after a shed frame, not sending the frames "
            "taken inside its Retry-After (*held*); *http*: they send every frame regardless. "
            "*of cap.*: served at 2x over the capacity measured in slices alternating with "
            "the phase's own (ABBA, "
            + str(data.get("slices", 1))
            + " of each; the machine's speed drifts within minutes), and in brackets over "
            "the first capacity, which set the offered load; *capacity between* lists the "
            "capacity of those slices.",
            "",
        ]
        rows = []
        for r in data["results"]:
            cap = r["capacity"]
            rows.append(
                [
                    f"{r['replicas']} ({r['database']})",
                    "capacity (closed loop)",
                    cap["served_per_s"],
                    "",
                    cap["p50_ms"],
                    cap["p99_ms"],
                    "",
                    "",
                    "",
                    "",
                    _cores(cap),
                    f"idle {r['idle_mb']:.0f} MB",
                ]
            )
            for name, run in r["runs"].items():
                v = run["verdicts"]
                met = [k for k, ok in v.items() if k.endswith("_met") and not ok]
                rows.append(
                    [
                        "",
                        f"2x: {r['vehicles']} x {r['rate_hz']:.1f} Hz, {name}",
                        run["served_per_s"],
                        f"{100 * v['served_share']:.0f} %"
                        + (
                            f" ({100 * v['served_share_of_first_capacity']:.0f} %)"
                            if "served_share_of_first_capacity" in v
                            else ""
                        ),
                        run["served_p50_ms"],
                        run["served_p99_ms"],
                        f"{v['p99_over_capacity_p50']:.1f}x",
                        f"{run['shed']}" + _held(run),
                        run["errors_5xx"] + run["failed_no_answer"],
                        run["writes_p99_s"],
                        _cores(run)
                        + (
                            f"; per core {100 * v['served_per_core_vs_capacity']:.0f} %"
                            if "served_per_core_vs_capacity" in v
                            else ""
                        ),
                        f"+{v['memory_growth_mb']:.0f} MB; "
                        + ("all met" if not met else "missed: " + ", ".join(met))
                        + (
                            f"; capacity between {v['capacity_interleaved_per_s']:.1f}/s"
                            if "capacity_interleaved_per_s" in v
                            else ""
                        ),
                    ]
                )
        header = ["replicas", "phase", "served/s", "of cap.", "p50 ms", "p99 ms"]
        header += ["p99 / cap. p50", "shed", "5xx / lost", "writes p99 s"]
        header += ["cores gen / srv / other", "memory, goals"]
        out += [table(header, rows), ""]
    out += ["## What one entry costs (bench/footprint.py)", ""]
    if footprint is None:
        out += ["not run", ""]
    else:
        i, st = footprint["index"], footprint["stored"]
        out += [
            table(
                ["what", "bytes per entry", "measured on"],
                [
                    [
                        "replica index (resident)",
                        i["rss_bytes_per_entry"],
                        f"{i['entries']} synthetic",
                    ],
                    ["index arrays (bare)", i["arrays_bytes_per_entry"], "arithmetic"],
                    ["entry cache", st["cache_bytes_per_entry"], f"{st['entries']} sim entries"],
                    [
                        "database blobs",
                        st["blob_bytes_total_per_entry"],
                        f"{st['mean_points']:.0f} points/entry",
                    ],
                    ["SQLite file", st.get("sqlite_file_bytes_per_entry"), "same"],
                ],
            ),
            "",
        ]
    return out


def closed_loop_section(scenario: str, data: dict | None) -> list[str]:
    lines = ["", f"## Closed loop, {scenario} (bench/closed_loop.py --scenario {scenario})", ""]
    if not data:
        return [*lines, "not run"]
    keys = (
        ("loc_rmse_m", "RMSE m"),
        ("loc_p95_m", "p95 m"),
        ("loc_max_m", "max m"),
        ("spikes", "spikes"),
        ("lateral_rmse_m", "lateral RMSE m"),
        ("lateral_max_m", "lateral max m"),
        ("lane_departures", "lane departures"),
        ("hypotheses_share", "frames with hypotheses"),
        ("corr_tracking_vs_loc_error", "corr(tracking, loc error)"),
    )
    rows = [[name, *(m.get(k) for k, _ in keys)] for name, m in data["cases"].items()]
    lines.append(table(["case", *(label for _, label in keys)], rows))
    lines += ["", f"Goals: {json.dumps(data.get('goals', {}), default=float)}", ""]
    for plot in data.get("plots", []):
        lines.append(f"![{Path(plot).stem}](results/{Path(plot).name})")
    return lines


def pnp_calibration_section(data: dict | None) -> list[str]:
    """The measurement model under three PnP strategies (bench/pnp_calibration.py)."""
    lines = ["", "## Guided PnP and the measurement model (bench/pnp_calibration.py)", ""]
    if not data:
        return lines + ["not run"]

    def std(v: list[float]) -> str:
        return f"{v[0]:.3f} / {v[1]:.3f} / {np.degrees(v[2]):.3f}"

    rows = [
        [
            name,
            r["accepted"],
            r["gated"],
            std(r["sigma1_std"]),
            std(r["robust_std"]),
            f"{r['over_0_5m']} / {r['over_1m']}",
            std(r["common_std"]),
            " / ".join(f"{c:.2f}" for c in r["intra_frame_correlation"]),
        ]
        for name, r in data["strategies"].items()
    ]
    header = [
        "PnP",
        "accepted",
        "beyond gates",
        "Sigma1 std (m, m, deg)",
        "robust std",
        "> 0.5 m / > 1 m",
        "same hypotheses std",
        "error corr. in a frame",
    ]
    lines.append(table(header, rows))
    changes = "; ".join(
        f"{what}: " + " / ".join(f"{100 * c:+.0f} %" for c in v)
        for what, v in data["sigma1_std_change"].items()
    )
    lines += [
        "",
        f"Training run of the seed-{data['seed']} {data['size']} city, {data['frames']} frames; "
        f"same hypotheses: the {data['common_hypotheses']} (query, entry) pairs every "
        f"strategy solved within {data['close_m']} m. Sigma1 std change (X / Y / psi): "
        f"{changes}.",
    ]
    return lines


def pnp_scale_section(data: dict | None) -> list[str]:
    """Per-entry PnP accuracy against the sim's true relative poses (bench/pnp_scale.py)."""
    lines = ["", "## Per-entry PnP against the true poses (bench/pnp_scale.py)", ""]
    if not data:
        return lines + ["not run"]
    names = {
        "unweighted": "plain (the entry's RANSAC)",
        "weighted": "keypoint scales as LM weights (opt-in)",
        "refined": "refined by projection (default)",
    }
    rows = []
    for label in ("day", "night"):
        run = data.get(label)
        if not run:
            continue
        inliers = run.get("inliers_median", {})
        for key, name in names.items():
            if key not in run:
                continue
            r = run[key]
            count = inliers.get(key, "-")
            rows.append([label, name, r["n"], r["median_m"], r["mean_m"], r["p75_m"], count])
    lines.append(
        table(["query", "pose", "entry poses", "median m", "mean m", "p75 m", "inliers"], rows)
    )
    lines += [
        "",
        f"Dataset {data.get('dataset')}, every {data.get('step')}th query frame; the same "
        "matches and RANSAC samples for each row; translation error of T_ref_from_query "
        "against the sim's true relative pose (inliers: median; '-' where not recorded).",
    ]
    kept = [
        f"{label} {data[label]['refined_inliers']['n']} inliers, "
        f"{100 * data[label]['refined_inliers']['wrong_share']:.1f} % beyond 3 px, median "
        f"{data[label]['refined_inliers']['median_residual_px']:.2f} px"
        for label in ("day", "night")
        if "refined_inliers" in data.get(label, {})
    ]
    if kept:
        lines += [
            "",
            "The refined poses' inliers under the true pose: " + "; ".join(kept) + ".",
        ]
    return lines


def error_split_section(runs: list[tuple[str, dict]]) -> list[str]:
    """What each recording error costs the localizer (bench/error_split.py): the default
    run (results/error_split.json) and any kept beside it (results/error_split_*.json)."""
    lines = ["", "## What each recording error costs (bench/error_split.py)", ""]
    if not runs:
        return lines + ["not run"]
    for name, data in runs:
        lines += error_split_table(name, data)
    return lines


def error_split_table(name: str, data: dict) -> list[str]:
    lines = [
        f"`results/{name}.json`: {data['size']} city, {data['frames_per_run']} frames per "
        "run, each group of the sim's recording errors on alone. Medians against the map's "
        "own frame (mm), then the filter against the written truth beside the floor (m).",
        "",
    ]
    rows = [
        [
            r["group"],
            r["seed"],
            round(r["filter_map_median_m"] * 1000, 1),
            round(r["best_of_k_map_median_m"] * 1000, 1),
            round(r["likeliest_map_median_m"] * 1000, 1),
            round(r["filter_over_best_of_k_map"], 2),
            round(r["filter_rmse_m"], 3),
            round(r["filter_median_m"], 3),
            round(r["floor_median_m"], 3),
        ]
        for r in data["rows"]
    ]
    header = ["errors on", "seed", "filter", "best of k", "likeliest", "ratio"]
    header += ["RMSE", "median", "floor median"]
    return lines + [table(header, rows), ""]


def joint_refit_section(data: dict | None) -> list[str]:
    """The joint pose's Cauchy refit against least squares (bench/joint_refit.py)."""
    lines = ["", "## The joint pose's Cauchy refit (bench/joint_refit.py)", ""]
    if not data:
        return lines + ["not run"]
    rows = [
        [
            name,
            f"{r['position_median_mm']:.2f}",
            f"{r['position_mean_mm']:.2f}",
            f"{r['position_p90_mm']:.2f}",
            f"{r['heading_median_deg']:.3f}",
            f"{r['localize_cpu_ms_p50']:.2f}",
        ]
        for name, r in data["rows"].items()
    ]
    lines.append(
        table(
            ["joint pose", "median mm", "mean mm", "p90 mm", "heading deg", "localize CPU ms"],
            rows,
        )
    )
    return lines + [
        "",
        f"Against the true poses of an error-free city ({data['dataset']}), on the "
        f"{data['frames_compared']} of {data['frames']} query frames where both passes give "
        f"a joint pose; the refit's median error {data['median_ratio']:.2f}x least squares'.",
    ]


def pose_covariance_section(data: dict | None) -> list[str]:
    """What the PnP pose covariance says about a hypothesis's error (bench/pose_covariance.py)."""
    lines = ["", "## PnP pose covariance against the error (bench/pose_covariance.py)", ""]
    if not data:
        return lines + ["not run"]
    rows = []
    # "query" / "night" (one covariance), or "<run>, <variant>" rows (both covariances)
    names = [k for k, v in data.items() if isinstance(v, dict) and "hypotheses" in v]
    for run in names:
        r = data[run]
        rows.append(
            [
                run,
                r["hypotheses"],
                r["spearman_error_vs_spread"],
                r["spearman_error_vs_inv_sqrt_inliers"],
                r["spearman_error_vs_reprojection"],
                " / ".join(f"{v:.3f}" for v in r["error_quartiles_m"]),
                " / ".join(f"{v:.3f}" for v in r["spread_quartiles_m"]),
                f"{100 * r['off_share_small_spread']:.1f} / "
                f"{100 * r['off_share_large_spread']:.1f}",
                r["pixel_noise_px"],
            ]
        )
    off = data.get("off_m", 0.3)
    lines.append(
        table(
            [
                "query",
                "hypotheses",
                "rho(error, spread)",
                "rho(error, 1/sqrt(inliers))",
                "rho(error, reproj.)",
                "error quartiles m",
                "spread quartiles m (1 px)",
                f"% > {off:g} m, smaller / larger spread half",
                "error / spread px",
            ],
            rows,
        )
    )
    lines += [
        "",
        f"Dataset {data.get('dataset')}, every frame, one search of the whole map; per-entry "
        "hypotheses; error against the entry's own map frame (the recording errors between "
        "runs left out); rho: Spearman rank correlation; spread: sqrt(var X + var Y) of the "
        "planar pose covariance from the hypothesis's own inliers at 1 px (every inlier at "
        "1 px, or each at 1 px times its keypoint's pyramid scale); error / spread: the "
        "pixel noise that would make the spread the error's size (median).",
    ]
    ratios = [
        f"{name.split(', ', 1)[1]} {data[name]['night_over_day_pixel_noise']:.2f}"
        for name in names
        if "night_over_day_pixel_noise" in data[name]
    ]
    if ratios:
        lines += [
            "",
            "Night / day error-to-spread ratio (1: one pixel noise fits day and night): "
            + "; ".join(ratios)
            + ".",
        ]
    return lines


# --- The README's results table ------------------------------------------------------
# One row per headline figure that bench/results/*.json holds, each beside its goal (or
# the paper's figure), with the date its results file was produced.

PAPER_KITTI_RMSE_M = 0.313  # docs/method.md section 10: KITTI 00, 85 % map / 15 % test
PAPER_RATE = "~10 Hz, worst 5 Hz, on an i7-9750H laptop CPU"
PAPER_INDOOR = "100 % < 0.1 m, ~92 % < 0.06 m"


@dataclass(frozen=True)
class Headline:
    """One row of the README's table: the figure (and the command that measures it), its
    value as measured, its goal or the paper's figure with the verdict, and the stem of
    the results file it is read from (whose date the row carries)."""

    figure: str
    value: str
    goal: str
    source: str


def _verdict(ok: bool) -> str:
    return "met" if ok else "**missed**"


def _not_run(figure: str, source: str) -> Headline:
    return Headline(figure, "not run", "-", source)


def accuracy_headlines(data: dict | None) -> list[Headline]:
    """Day query, filter / best-of-k and night of the urban city (bench/accuracy.py)."""
    source = "accuracy_urban"
    if data is None:
        return [_not_run("Position RMSE, medium sim city (`python -m bench.accuracy`)", source)]
    goals, floors = data.get("goals", {}), data.get("goals_floor", {})
    full = data["query"]["full"]
    seed = data.get("seed", "?")

    def floor(name: str) -> str:
        return f" (floor {floors[name]:.3f} m)" if name in floors else ""

    rmse, median = full["position_rmse_m"], full["position_median_m"]
    rows = [
        Headline(
            f"Position RMSE, medium sim city with recording errors, query run, seed {seed} "
            "(`python -m bench.accuracy`)",
            f"{rmse:.3f} m" + floor("position RMSE (m)"),
            f"<= {goals['position_rmse_m']:g} m: {_verdict(rmse <= goals['position_rmse_m'])}; "
            f"paper {PAPER_KITTI_RMSE_M} m on KITTI 00",
            source,
        ),
        Headline(
            "Position median, same run",
            f"{median:.3f} m" + floor("position median (m)"),
            f"<= {goals['position_median_m']:g} m: "
            f"{_verdict(median <= goals['position_median_m'])}",
            source,
        ),
        Headline(
            "Heading RMSE / frames within 0.25 m and 2 deg, same run",
            f"{full['heading_rmse_deg']:.2f} deg / {100 * full['within_0_25m_2deg']:.0f} %",
            f"<= {goals['heading_rmse_deg']:g} deg: "
            f"{_verdict(full['heading_rmse_deg'] <= goals['heading_rmse_deg'])} / "
            f">= {100 * goals['within_0_25m_2deg']:.0f} %: "
            f"{_verdict(full['within_0_25m_2deg'] >= goals['within_0_25m_2deg'])}",
            source,
        ),
    ]
    frames = data.get("bias", {}).get("frames_with_hypotheses", {})
    if frames.get("best_of_k_median_m") and frames.get("full_median_m") is not None:
        ratio = frames["full_median_m"] / frames["best_of_k_median_m"]
        goal = goals["filter_median_over_best_of_k"]
        name = "filter / best-of-k median"
        note = ""
        if ratio > goal and name in floors and goal < floors[name]:
            note = " (the goal lies under the floor)"
        rows.append(
            Headline(
                "Filter median / the best of the 10 hypotheses' median (picked with the truth)",
                f"{ratio:.2f}" + (f" (floor {floors[name]:.2f})" if name in floors else ""),
                f"<= {goal:g}: {_verdict(ratio <= goal)}{note}",
                source,
            )
        )
    night = data.get("night", {}).get("night, + night entries")
    if night and night.get("position_rmse_m") is not None and rmse:
        ratio = night["position_rmse_m"] / rmse
        seeds = data.get("filter_seeds")
        extra = ""
        if seeds:
            mean = sum(seeds["night_rmse_m"]) / sum(seeds["day_rmse_m"])
            extra = f" (filter seeds 0-{len(seeds['day_rmse_m']) - 1}: {mean:.2f}x)"
        goal = goals["night_rmse_over_day"]
        rows.append(
            Headline(
                "Night query after night images were added, RMSE over the day's",
                f"{ratio:.2f}x{extra}",
                f"<= {goal:g}x: {_verdict(ratio <= goal)}",
                source,
            )
        )
    return rows


def indoor_headline(data: dict | None) -> Headline:
    """The 1:10 indoor track (bench/accuracy.py --scenario indoor), beside the paper's."""
    figure = (
        "Indoor 1:10 track, open loop, position RMSE (`python -m bench.accuracy --scenario indoor`)"
    )
    if data is None:
        return _not_run(figure, "accuracy_indoor")
    full, shares = data["query"]["full"], data.get("full_error_shares", {})
    paper = data.get("paper", {})
    value = f"{full['position_rmse_m']:.4f} m"
    goal = f"paper {PAPER_INDOOR}"
    if "within_0_1m" in shares and "within_0_06m" in shares:
        value += (
            f"; {100 * shares['within_0_1m']:.0f} % < 0.1 m, "
            f"{100 * shares['within_0_06m']:.0f} % < 0.06 m"
        )
        if "open_loop_within_0_06m" in paper:
            ok = shares["within_0_1m"] >= paper["open_loop_within_0_1m"] and (
                shares["within_0_06m"] >= paper["open_loop_within_0_06m"]
            )
            goal += f": {_verdict(ok)}"
    return Headline(figure, value, goal, "accuracy_indoor")


def localize_headline(data: dict | None) -> Headline:
    """One frame on one core without a prior (bench/localize.py)."""
    figure = "Localize one frame, one core, no prior, p50 (`python -m bench.localize`)"
    if data is None or "met" not in data.get("goals", {}):
        return _not_run(figure, "localize")
    g = data["goals"]
    met = g["met"]
    value = (
        f"{g['total_p50_ms']:.1f} ms, {g['total_over_features']:.2f}x the blur+ORB stage, "
        f"{g['paper_over_total']:.1f}x faster than the paper-faithful pipeline"
    )
    goal = (
        f"<= {data.get('target_p50_ms', 20.0):g} ms: {_verdict(met['p50_target'])}, "
        f"<= 2x ORB: {_verdict(met['x_features'])}, >= 5x: {_verdict(met['x_paper'])}; "
        f"paper {PAPER_RATE}"
    )
    return Headline(figure, value, goal, "localize")


def filter_headline(data: dict | None) -> Headline:
    figure = "Filter step, 1000 particles, 10 hypotheses (`python -m bench.filter`)"
    if data is None:
        return _not_run(figure, "filter")
    figure = (
        f"Filter step, {data['n_particles']} particles, {data['n_hypotheses']} hypotheses "
        "(`python -m bench.filter`)"
    )
    ms, goal = data["step_p50_ms"], data["target_step_ms"]
    return Headline(figure, f"{ms:.2f} ms", f"<= {goal:g} ms: {_verdict(ms <= goal)}", "filter")


def ingest_headline(data: dict | None) -> Headline:
    figure = "Ingestion of KITTI frames (`python -m bench.ingest`)"
    if data is None or not data.get("variants"):
        return _not_run(figure, "ingest")
    name, best = max(data["variants"].items(), key=lambda kv: kv[1]["median_fps"])
    fps, goal = best["median_fps"], data["target_fps"]
    return Headline(
        f"Ingestion of KITTI frames, {name} (`python -m bench.ingest`)",
        f"{fps:.0f} frames/s",
        f">= {goal:g}: {_verdict(fps >= goal)}",
        "ingest",
    )


def retrieval_headline(data: dict | None) -> Headline:
    figure = "Retrieval, the largest map measured (`python -m bench.retrieval`)"
    if data is None or not data.get("sizes"):
        return _not_run(figure, "retrieval")
    size = max(data["sizes"], key=lambda r: r["entries"])
    goal = data["goal"]
    n = size["entries"]
    entries = f"{n / 1e6:g}M" if n >= 1_000_000 else f"{n / 1e3:g}k"
    ok = size["p50_ms"] <= goal["p50_ms"] and size["recall_at_10"] >= goal["recall_at_10"]
    return Headline(
        f"Retrieval over {entries} entries, p50 / recall@10 against exact float search "
        "(`python -m bench.retrieval`)",
        f"{size['p50_ms']:.2f} ms / {size['recall_at_10']:.3f}",
        f"<= {goal['p50_ms']:g} ms / >= {goal['recall_at_10']:g}: {_verdict(ok)}",
        "retrieval",
    )


def index_memory_headline(data: dict | None) -> Headline:
    """Replica index memory per entry at the largest size of bench/footprint.py (its own,
    anonymous memory), beside the float-resident baseline when the same run measured it."""
    figure = "Replica retrieval index, resident bytes per entry (`python -m bench.footprint`)"
    sizes = (data or {}).get("index_sizes") or []
    if not sizes:
        return _not_run(figure, "footprint")
    size = max(sizes, key=lambda r: r["entries"])
    n, per_entry = size["entries"], size["product"]["anon_bytes_per_entry"]
    entries = f"{n / 1e6:g}M" if n >= 1_000_000 else f"{n / 1e3:g}k"
    value = f"{per_entry:,.0f} B at {entries} entries"
    baselines = [r for r in sizes if "baseline_2026_12_01" in r]
    if baselines:
        b = max(baselines, key=lambda r: r["entries"])
        value += (
            f" (float-resident index: {b['baseline_2026_12_01']['anon_bytes_per_entry']:,.0f} B"
            f" at {b['entries'] / 1e3:g}k)"
        )
    return Headline(figure, value, f"<= 2,048 B: {_verdict(per_entry <= 2048)}", "footprint")


def load_headline(data: dict | None) -> Headline:
    """Fleet load at twice capacity (bench/load.py): the served share over HTTP and over
    the stream, the worst p99, and how many phases missed a goal."""
    figure = "Fleet load at 2x capacity, share of capacity served (`python -m bench.load`)"
    if data is None or not data.get("results"):
        return _not_run(figure, "load")
    http, stream, p99, missed, phases = [], [], [], 0, 0
    for setup in data["results"]:
        for name, run in setup["runs"].items():
            v = run["verdicts"]
            (stream if name.startswith("ws") else http).append(v["served_share"])
            p99.append(v["p99_over_capacity_p50"])
            phases += 1
            missed += not all(ok for key, ok in v.items() if key.endswith("_met"))

    def span(shares: list[float]) -> str:
        return f"{100 * min(shares):.0f}-{100 * max(shares):.0f} %"

    parts = [f"{span(http)} over HTTP"] if http else []
    parts += [f"{span(stream)} over the stream"] if stream else []
    g = data["goals"]
    return Headline(
        figure,
        ", ".join(parts) + f"; p99 <= {max(p99):.1f}x the capacity p50",
        f">= {100 * g['served_share_min']:.0f} %, p99 <= {g['p99_over_capacity_p50_max']:g}x: "
        + ("met in every phase" if not missed else f"**missed** in {missed} of {phases} phases"),
        "load",
    )


def overload_headline(data: dict | None, name: str) -> Headline:
    """Issue 50's overload (bench/load.py --overloads 3 5): the share of the capacity
    served at the highest and lowest offered multiple and the share of shed frames
    answered within 50 ms, over every run (vehicles sending every frame or honouring
    Retry-After); ``name`` the results file (with or without nginx in front)."""
    front = (data or {}).get("server", {}).get("front") or (
        "nginx" if name.endswith("_nginx") else "none"
    )
    figure = (
        "Overload at 3x / 5x capacity, share served and shed answered within 50 ms "
        f"(`python -m bench.load --overloads 3 5{' --front nginx' if front == 'nginx' else ''}`"
        f"{', nginx in front' if front == 'nginx' else ', one bare replica'})"
    )
    if data is None or not data.get("results"):
        return _not_run(figure, name)
    served, within, ok = [], [], True
    for setup in data["results"]:
        for run in setup["runs"].values():
            served.append(run["verdicts"]["served_share"])
            within.append(run["shed_within_50ms"] if run["shed"] else 1.0)
    ok = min(served) >= 0.9 and min(within) >= 0.99
    return Headline(
        figure,
        f"served {100 * min(served):.1f}-{100 * max(served):.1f} %, shed within 50 ms "
        f"{100 * min(within):.1f}-{100 * max(within):.1f} %",
        f">= 90 %, every shed within 50 ms (99 %): {_verdict(ok)}",
        name,
    )


def fleet_camera_headline(data: dict | None) -> Headline:
    """A fleet car's camera (issue 48) against the mapping camera's lap on the same street
    (bench/accuracy.py --scenario fleet)."""
    figure = (
        "Fleet camera (1024x576, f 640 px, plumb_bob, 0.23 m lower, 3 deg down), raw lap "
        "RMSE over the mapping camera's (`python -m bench.accuracy --scenario fleet`)"
    )
    if data is None or data.get("raw_over_mapping_rmse") is None:
        return _not_run(figure, "accuracy_fleet")
    laps = data["laps"]
    mapping = laps["mapping camera"]["position_rmse_m"]
    raw = laps["fleet camera, raw (lens model sent)"]["position_rmse_m"]
    ratio, goal = data["raw_over_mapping_rmse"], data["goal_raw_over_mapping_rmse"]
    value = f"{ratio:.2f}x ({raw:.3f} m vs {mapping:.3f} m)"
    pinhole = laps.get("fleet camera, raw read as pinhole", {}).get("position_rmse_m")
    if pinhole is not None:
        value += f"; read as pinhole {pinhole:.2f} m"
    return Headline(figure, value, f"<= {goal:g}x: {_verdict(ratio <= goal)}", "accuracy_fleet")


def lens_headline(data: dict | None) -> Headline:
    """The server's time per distorted query over a pinhole one (bench/lens.py)."""
    figure = (
        "Server CPU time per distorted query over the same frames undistorted, one core "
        "(`python -m bench.lens`)"
    )
    if data is None:
        return _not_run(figure, "lens")
    ratio, goal = data["distorted_over_pinhole_mean"], data["goal_distorted_over_pinhole"]
    per_query = data["per_query"]
    value = (
        f"{ratio:.3f}x ({per_query['distorted']['mean_ms']:.1f} vs "
        f"{per_query['pinhole']['mean_ms']:.1f} ms)"
    )
    return Headline(figure, value, f"<= {goal:g}x: {_verdict(ratio <= goal)}", "lens")


def headline_rows(results: Path = RESULTS) -> list[Headline]:
    """The README's rows, read from ``results`` (a directory of bench result files)."""
    return [
        *accuracy_headlines(load("accuracy_urban", results)),
        indoor_headline(load("accuracy_indoor", results)),
        localize_headline(load("localize", results)),
        fleet_camera_headline(load("accuracy_fleet", results)),
        lens_headline(load("lens", results)),
        filter_headline(load("filter", results)),
        ingest_headline(load("ingest", results)),
        retrieval_headline(load("retrieval", results)),
        index_memory_headline(load("footprint", results)),
        load_headline(load("load", results)),
        overload_headline(load("load_overload", results), "load_overload"),
        overload_headline(load("load_overload_nginx", results), "load_overload_nginx"),
    ]


def result_date(path: Path) -> str | None:
    """When a results file was produced (YYYY-MM-DD): the date of the commit that last
    wrote it when it is committed unchanged (a checkout resets file times), else its
    modification time; None when it does not exist."""
    if not path.exists():
        return None
    try:
        status = subprocess.run(
            ["git", "status", "--porcelain", "--", path.name],
            cwd=path.parent,
            capture_output=True,
            text=True,
            check=True,
        ).stdout
        if not status.strip():
            committed = subprocess.run(
                ["git", "log", "-1", "--format=%cs", "--", path.name],
                cwd=path.parent,
                capture_output=True,
                text=True,
                check=True,
            ).stdout.strip()
            if committed:
                return committed
    except (OSError, subprocess.CalledProcessError):
        pass  # not a git checkout: the file's own time
    return time.strftime("%Y-%m-%d", time.localtime(path.stat().st_mtime))


def _cpu_model_now() -> str:
    """The CPU model of the machine running this (Linux's /proc/cpuinfo, else platform)."""
    try:
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                return line.split(":", 1)[1].strip()
    except OSError:
        pass
    return platform.processor() or platform.machine() or "unknown CPU"


def machine_summary(results: Path = RESULTS) -> str:
    """The machine the results were measured on, as the results files record it (cores,
    platform, CPU model), completed by this machine's CPU model where none is recorded."""
    cores, platforms, models = set(), set(), set()
    for path in sorted(results.glob("*.json")):
        data = json.loads(path.read_text())
        if not isinstance(data, dict):
            continue
        machine = data.get("machine")
        if isinstance(machine, dict):
            cores.add(machine.get("cpus"))
            platforms.add(machine.get("platform"))
            models.add(machine.get("cpu_model"))
        elif isinstance(machine, str):
            platforms.add(machine)
        cores.add(data.get("cpu_count"))
        models.add(data.get("cpu_model"))
    cores.discard(None)
    platforms.discard(None)
    models.discard(None)
    systems = sorted(
        {
            " ".join(p for p in (s.split("-")[0], "x86_64" if "x86_64" in s else "") if p)
            for s in platforms
        }
    )
    text = (
        f"{'/'.join(str(c) for c in sorted(cores))} cores" if cores else f"{os.cpu_count()} cores"
    )
    if systems:
        text += f", {', '.join(systems)}"
    if models:
        text += f", {', '.join(sorted(models))}"
    else:
        text += (
            f" (the results do not record the CPU model; this table was generated on "
            f"{_cpu_model_now()}, {os.cpu_count()} cores)"
        )
    return text


def results_table(results: Path = RESULTS) -> str:
    """The README's results section (Markdown): when and where, then the table."""
    rows = headline_rows(results)
    dates = {row.source: result_date(results / f"{row.source}.json") for row in rows}
    produced = sorted(d for d in dates.values() if d)
    when = (
        "no results yet"
        if not produced
        else produced[0]
        if produced[0] == produced[-1]
        else f"between {produced[0]} and {produced[-1]}"
    )
    lines = [
        f"Measured on the sim (not a real street), one thread per stage, {when} (each row's "
        f"date beside it), on {machine_summary(results)}. Generated by `python -m bench.report` "
        "from `bench/results/*.json`; every table in full: `bench/REPORT.md`.",
        "",
        "| figure | measured | goal or paper | date |",
        "| --- | --- | --- | --- |",
    ]
    lines += [f"| {r.figure} | {r.value} | {r.goal} | {dates[r.source] or '-'} |" for r in rows]
    return "\n".join(lines)


def write_results_section(readme: Path, section: str) -> bool:
    """Put ``section`` between the README's results markers, leaving every other byte of
    the file as it was. Returns whether the file changed; raises ValueError when the
    markers are missing, repeated or out of order."""
    text = readme.read_text()
    if text.count(RESULTS_BEGIN) != 1 or text.count(RESULTS_END) != 1:
        raise ValueError(f"{readme} needs one {RESULTS_BEGIN} and one {RESULTS_END}")
    start = text.index(RESULTS_BEGIN) + len(RESULTS_BEGIN)
    end = text.index(RESULTS_END)
    if end < start:
        raise ValueError(f"{readme}: {RESULTS_END} comes before {RESULTS_BEGIN}")
    new = text[:start] + "\n" + section.strip("\n") + "\n" + text[end:]
    if new == text:
        return False
    readme.write_text(new)
    return True


def main() -> None:
    lines = [
        "# monoloc benchmark report",
        "",
        f"Generated by `python -m bench.report` (the last step of `make bench`) on "
        f"{time.strftime('%Y-%m-%d %H:%M')} from bench/results/*.json, measured on "
        f"{machine_summary()}; one thread per stage unless stated.",
        "",
    ]
    vision = load("vision")
    lines += ["## Vision core, one thread (bench/vision.py)", ""]
    if vision:
        rows = [
            [
                k,
                s["p50_ms"],
                s["baseline_p50_ms"],
                s["baseline"],
                s["target_ms"],
                "met" if s["pass"] else "**missed**",
            ]
            for k, s in vision["stages"].items()
        ]
        lines.append(table(["stage", "p50 ms", "baseline ms", "baseline", "target ms", ""], rows))
    else:
        lines.append("not run")
    loc = load("localize")
    lines += ["", "## Localization per query, one core (bench/localize.py)", ""]
    if loc:
        st = loc["stages"]
        names = [n for n in ("monoloc", "streaming", "independent", "paper") if n in st]
        heads = {
            "monoloc": "monoloc, no prior",
            "streaming": "monoloc, streaming with filter prior",
            "independent": "independent PnP, no prior",
            "paper": "paper-faithful",
        }
        rows = [
            [k] + [f"{st[n][k]['p50_ms']:.2f} / {st[n][k]['p99_ms']:.1f}" for n in names]
            for k in st["monoloc"]
        ]
        lines.append(table(["stage (p50 / p99 ms)"] + [heads[n] for n in names], rows))
        share, recall = loc.get("share_within_0_3m", {}), loc.get("recall_at_10", {})
        if share:
            lines += [
                "",
                "Best hypothesis within 0.3 m: "
                + ", ".join(f"{heads[n]} {share[n]:.2f}" for n in names if n in share)
                + "; recall@10 (2 m): "
                + ", ".join(f"{heads[n]} {recall[n]:.2f}" for n in names if n in recall)
                + ".",
            ]
        goals = loc.get("goals", {})
        if "met" in goals:
            met = goals["met"]
            stream = goals.get("streaming")

            def also(key, fmt):
                if not stream:
                    return ""
                return f" (streaming with filter prior: {fmt.format(stream[key])})"

            lines += [
                "",
                f"Goals of issue 17, judged on {goals.get('basis', 'monoloc without a prior')}:",
                "",
                f"- p50 <= 2.0x blur+ORB: {'met' if met['x_features'] else '**missed**'}, "
                f"{goals['total_over_features']:.2f}x" + also("total_over_features", "{:.2f}x"),
                f"- >= 5x faster than paper-faithful: {'met' if met['x_paper'] else '**missed**'}, "
                f"{goals['paper_over_total']:.2f}x" + also("paper_over_total", "{:.2f}x"),
                f"- p99 <= 2x p50: {'met' if met['p99_over_p50'] else '**missed**'}, "
                f"{goals['p99_over_p50']:.2f}x" + also("p99_over_p50", "{:.2f}x"),
                f"- p50 <= 20 ms: {'met' if met['p50_target'] else '**missed**'}, "
                f"{goals['total_p50_ms']:.1f} ms" + also("total_p50_ms", "{:.1f} ms"),
            ]
        priors = loc.get("streaming_priors")
        if priors:
            lines += [
                "",
                f"Streaming priors: the client's particle filter driven over the "
                f"{priors['frames_driven']} frames of the query run in the warm-up pass; "
                f"{priors['queries_with_heading']} of {loc['queries']} query frames had a "
                f"prior with a heading, median {priors['median_prior_error_m']:.2f} m from "
                "the truth.",
            ]
    else:
        lines.append("not run")
    speed = load("speed")
    lines += ["", "## End to end through the server (bench/speed.py)", ""]
    if speed:
        rows = [
            [
                name,
                r["worker_threads"],
                r["vehicles"],
                r["server"]["total"]["p50_ms"],
                r["server"]["total"]["p99_ms"],
                r["round_trip"]["p50_ms"],
                r["round_trip"]["p99_ms"],
                r["frames_per_s"],
                r["share_with_hypotheses"],
            ]
            for name, r in speed["runs"].items()
        ]
        lines.append(
            table(
                [
                    "run",
                    "worker threads",
                    "vehicles",
                    "server p50 ms (incl. decode)",
                    "server p99 ms",
                    "round trip p50 ms",
                    "round trip p99 ms",
                    "frames/s",
                    "frames with hypotheses",
                ],
                rows,
            )
        )
        lines += [
            "",
            f"Speed-up over the paper-faithful pipeline: "
            f"{json.dumps({k: round(v, 2) for k, v in speed['speedup_vs_paper'].items()})}"
            f"; targets met: {json.dumps(speed['target_met'])}.",
        ]
    else:
        lines.append("not run")
    retr = load("retrieval")
    lines += ["", "## Retrieval at scale (bench/retrieval.py)", ""]
    if retr:
        rows = [
            [
                r["entries"],
                r["index_kind"],
                r["p50_ms"],
                r["p99_ms"],
                "-" if r.get("p50_ms_two_threads") is None else r["p50_ms_two_threads"],
                r["baseline_exact_float_p50_ms"],
                r["memory_bytes_per_entry"],
                r["recall_at_10"],
            ]
            for r in retr["sizes"]
        ]
        lines.append(
            table(
                [
                    "entries",
                    "index",
                    "p50 ms",
                    "p99 ms",
                    "p50 ms, 2 threads",
                    "exact float p50 ms",
                    "bytes/entry",
                    "recall@10",
                ],
                rows,
            )
        )
        lines += [
            "",
            "Goal at 1M: p50 <= 2 ms and recall@10 >= 0.95 (synthetic route-like "
            "VLADs; see the script's docstring).",
        ]
    else:
        lines.append("not run")
    lines += pnp_calibration_section(load("pnp_calibration"))
    lines += pnp_scale_section(load("pnp_scale"))
    lines += pose_covariance_section(load("pose_covariance"))
    lines += joint_refit_section(load("joint_refit"))
    split_names = ["error_split"] + sorted(p.stem for p in RESULTS.glob("error_split_*.json"))
    splits = [(name, load(name)) for name in split_names]
    lines += error_split_section([(name, data) for name, data in splits if data])
    lines += [""] + fleet_section(load("load"), load("footprint"))
    for name in ("filter", "ingest", "sim"):
        data = load(name)
        lines += ["", f"## {name} (bench/{name}.py)", ""]
        lines.append(f"```\n{json.dumps(data, indent=1)[:2000]}\n```" if data else "not run")
    lines.append("")
    for scenario in ("urban", "indoor"):
        data = load(f"accuracy_{scenario}")
        lines += accuracy_section(scenario, data)
        plot = plot_accuracy(data, scenario)
        if plot:
            lines += [f"![accuracy {scenario}]({plot})", ""]
    stereo = load("stereo")
    if stereo:
        seed, frames = stereo.get("seed", "?"), stereo.get("frames_per_run", "?")
        lines += [f"## Stereo vs LiDAR maps, {stereo.get('size')} city, seed {seed}", ""]
        lines += [f"{frames} frames per run, from `python -m bench.stereo`.", ""]
        lines += [*stereo_lines(stereo), ""]
    lines += crash_section(load("crash"))
    lines += hostile_section(load("hostile"))
    lines += formats_section(load("formats"), load("geopose"))
    lines += http_overhead_section(load("http_overhead"))
    for scenario in ("indoor", "urban"):
        lines += closed_loop_section(scenario, load(f"closed_loop_{scenario}"))
    (HERE / "REPORT.md").write_text("\n".join(lines) + "\n")
    print(f"wrote {HERE / 'REPORT.md'}")
    changed = write_results_section(README, results_table())
    print(f"{'wrote' if changed else 'unchanged:'} the results table of {README}")


if __name__ == "__main__":
    main()
