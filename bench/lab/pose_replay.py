"""Lab tool: the pose stage (and matching) of bench.frame_cost's query frames, captured once
and replayed on whatever code is imported, to time it in CPU ms and to compare its
outputs between two trees (docs/notebook/frame_cost.md).

    python -m bench.lab.pose_replay capture DATA OUT.pkl   # DATA: bench.frame_cost --data
    python -m bench.lab.pose_replay replay IN.pkl OUT.pkl [--reps 5]
        [--projection-guided refit|once]
    python -m bench.lab.pose_replay compare A.pkl B.pkl
    python -m bench.lab.pose_replay errors IN.pkl A.pkl [B.pkl ...]

capture: each environment's map ingested as bench.frame_cost does, its 40 (25) query frames
as JPEG 90 pixels through ``MapRegistry.localize``, the pose stage's arguments and the
matching inputs recorded. replay: per frame the pose stage on those arguments (a fresh
``default_rng(seed)``) and the matching of the frame's entries, thread CPU time, the
mean over frames of each frame's minimum over ``--reps`` (robust to other processes on
the 2 cores); ``--projection-guided``: a lab variant of bench.lab.projection_guided (its
guided entries refit again by projection or not), its on-demand matching timed apart.
compare: frames whose hypotheses differ in method, entry, inlier or match counts, the
largest pose difference otherwise. errors: per-frame errors against the truth (the
hypothesis with the most inliers, the joint pose, every per-entry one). A replay run
from another tree (a copy of HEAD on the import path) gives the "before".
"""

from __future__ import annotations

import argparse
import pickle
import tempfile
import time
from pathlib import Path

import numpy as np


def capture(data: Path, out: Path) -> None:
    import cv2

    from bench.frame_cost import environments, ingest, query_frames
    from monoloc.server.localize import LocalizeConfig
    from monoloc.server.localize.frame import FrameStages
    from monoloc.server.localize.poses import pose_hypotheses
    from monoloc.server.map_registry import MapRegistry
    from monoloc.server.settings import Settings
    from monoloc.server.storage.db import create_engine_for, make_session_factory
    from monoloc.server.vision.matching import match_against_references

    captured = {}
    for env in environments(None, data):
        frames, current = [], {}

        def poses(*args, current=current):
            current["args"] = args
            return pose_hypotheses(*args)

        def match(query, refs, config, current=current):
            current["match"] = (query, list(refs), config)
            return match_against_references(query, refs, config)

        with tempfile.TemporaryDirectory() as tmp:
            map_id = ingest(Path(tmp), env)
            settings = Settings(data_dir=Path(tmp))
            registry = MapRegistry(
                make_session_factory(create_engine_for(settings)),
                settings.index_dir,
                version_check_s=1e9,
            )
            for i, (body, truth, _) in enumerate(query_frames(env, 40)):
                image = cv2.imdecode(np.frombuffer(body["jpeg90"], np.uint8), 0)
                seed = 1000 + i
                registry.localize(
                    map_id,
                    image,
                    LocalizeConfig(),
                    np.random.default_rng(seed),
                    stages=FrameStages(match=match, poses=poses),
                )
                args = list(current["args"])
                args[6] = None  # the rng: a fresh default_rng(seed) at each replay
                frames.append(
                    {"truth": truth, "seed": seed, "pose_args": args, "match": current["match"]}
                )
        captured[env.name] = frames
        print(f"{env.name}: {len(frames)} frames", flush=True)
    out.write_bytes(pickle.dumps(captured))


def replay(path: Path, out: Path, reps: int, projection_guided: str | None) -> None:
    from monoloc.server.vision.matching import match_against_references

    if projection_guided:
        from bench.lab import projection_guided as lab
        from bench.lab.projection_guided import EntryMatches

        stage = {
            "refit": lab.projection_guided_pose_hypotheses,
            "once": lab.projection_guided_once,
        }[projection_guided]
    else:
        from monoloc.server.localize.poses import pose_hypotheses as stage
    captured = pickle.loads(path.read_bytes())
    results = {}
    for name, frames in captured.items():

        def once(f):
            args = list(f["pose_args"])
            args[6] = np.random.default_rng(f["seed"])
            started = time.thread_time()
            if projection_guided:
                args[2] = EntryMatches(*f["match"])
                hyps, rejected = stage(*args)
                total = (time.thread_time() - started) * 1e3
                return hyps, rejected, total - args[2].elapsed_ms, args[2].elapsed_ms
            hyps, rejected = stage(*args)
            posed = time.thread_time()
            match_against_references(*f["match"])
            matched = time.thread_time()
            return hyps, rejected, (posed - started) * 1e3, (matched - posed) * 1e3

        for f in frames:  # warm-up: kernels loaded, caches filled
            once(f)
        pose_ms = np.empty((reps, len(frames)))
        match_ms = np.empty((reps, len(frames)))
        hyps_all, rejected_all = [], []
        for r in range(reps):
            for i, f in enumerate(frames):
                hyps, rejected, pose_ms[r, i], match_ms[r, i] = once(f)
                if r == 0:
                    hyps_all.append(hyps)
                    rejected_all.append(list(rejected))
        pose_min, match_min = pose_ms.min(axis=0), match_ms.min(axis=0)
        results[name] = {"hyps": hyps_all, "rejected": rejected_all}
        print(
            f"{name[:52]:52} CPU ms a frame (mean of per-frame minima over {reps}): "
            f"pose stage {pose_min.mean():.2f}, matching {match_min.mean():.2f}, "
            f"both {(pose_min + match_min).mean():.2f}",
            flush=True,
        )
    out.write_bytes(pickle.dumps(results))


def _key(hyps):
    return [(h.method, h.entry_id, h.n_inliers, h.n_matches, h.entry_ids) for h in hyps]


def compare(path_a: Path, path_b: Path) -> None:
    a, b = pickle.loads(path_a.read_bytes()), pickle.loads(path_b.read_bytes())
    for name in a:
        pairs = list(zip(a[name]["hyps"], b[name]["hyps"], strict=True))
        discrete = sum(_key(x) != _key(y) for x, y in pairs)
        rejected_pairs = zip(a[name]["rejected"], b[name]["rejected"], strict=True)
        rejected = sum(x != y for x, y in rejected_pairs)
        same = [(x, y) for x, y in pairs if _key(x) == _key(y)]
        d_pose = max(
            (np.abs(h.T_world_from_cam - g.T_world_from_cam).max() for x, y in same
             for h, g in zip(x, y, strict=True)),
            default=0.0,
        )  # fmt: skip
        print(
            f"{name[:52]:52} {len(pairs)} frames: {discrete} differ in method / entry / "
            f"inliers / matches, {rejected} in their rejections; the others' poses within "
            f"{d_pose:.1e}"
        )


def errors(captured_path: Path, *paths: Path) -> None:
    captured = pickle.loads(captured_path.read_bytes())
    runs = [(p.name, pickle.loads(p.read_bytes())) for p in paths]
    for name, frames in captured.items():
        print(name)
        for label, run in runs:
            best, joint, per_entry, n = [], [], [], []
            for f, hyps in zip(frames, run[name]["hyps"], strict=True):
                entries = [h for h in hyps if not h.joint]
                n.append(len(entries))
                err = [float(np.hypot(*(h.pose_world[:2] - f["truth"]))) for h in entries]
                per_entry += err
                best.append(err[int(np.argmax([h.n_inliers for h in entries]))] if err else np.inf)
                j = [h for h in hyps if h.joint]
                joint.append(np.hypot(*(j[0].pose_world[:2] - f["truth"])) if j else np.inf)
            print(
                f"  {label:24} hypotheses a frame {np.mean(n):.2f}; median error: most "
                f"inliers {np.median(best):.4f} m, joint {np.median(joint):.4f} m, every "
                f"per-entry one {np.median(per_entry):.4f} m "
                f"(p90 {np.percentile(per_entry, 90):.3f})"
            )


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    sub = parser.add_subparsers(dest="command", required=True)
    p = sub.add_parser("capture")
    p.add_argument("data", type=Path)
    p.add_argument("out", type=Path)
    p = sub.add_parser("replay")
    p.add_argument("captured", type=Path)
    p.add_argument("out", type=Path)
    p.add_argument("--reps", type=int, default=5)
    p.add_argument("--projection-guided", choices=("refit", "once"), default=None)
    p = sub.add_parser("compare")
    p.add_argument("a", type=Path)
    p.add_argument("b", type=Path)
    p = sub.add_parser("errors")
    p.add_argument("captured", type=Path)
    p.add_argument("runs", type=Path, nargs="+")
    args = parser.parse_args()
    from bench.accuracy import limit_threads

    limit_threads()
    if args.command == "capture":
        capture(args.data, args.out)
    elif args.command == "replay":
        replay(args.captured, args.out, args.reps, args.projection_guided)
    elif args.command == "compare":
        compare(args.a, args.b)
    else:
        errors(args.captured, *args.runs)


if __name__ == "__main__":
    main()
