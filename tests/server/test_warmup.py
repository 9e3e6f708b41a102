"""Cold start: after the server's warm-up (which `monoloc serve` and `monoloc localize` run
before their first query) every compiled kernel a query can call is loaded, so no query
pays for compiling or loading one. Checked in a fresh process."""

from __future__ import annotations

import json
import subprocess
import sys

_PROBE = """
import json
from numba.core.registry import CPUDispatcher
from monoloc.server import _png_kernel
from monoloc.server.index import _scan_kernel
from monoloc.server.vision import (
    _covariance_kernel, _hamming_kernel, _pnp_kernel, _vlad_kernel, _window_kernel,
)
from monoloc.server.index.warmup import warm_up as warm_up_index
from monoloc.server.vision.warmup import warm_up as warm_up_vision

WARM = {warm}
# kernels only other kernels call (numba compiles them into their caller's code)
KERNEL_CALLEES = {{"monoloc.server.vision._covariance_kernel.pose_information"}}
if WARM:
    warm_up_vision()
    warm_up_index()
kernels = {{}}
for module in (
    _covariance_kernel, _hamming_kernel, _png_kernel, _pnp_kernel, _scan_kernel, _vlad_kernel,
    _window_kernel,
):
    for name, obj in vars(module).items():
        if isinstance(obj, CPUDispatcher) and obj.__module__ == module.__name__:
            if obj.targetoptions.get("inline") == "always":
                continue  # inlined into its callers, never called on its own
            if f"{{module.__name__}}.{{name}}" in KERNEL_CALLEES:
                continue  # compiled into the one kernel that calls it
            kernels[f"{{module.__name__}}.{{name}}"] = len(obj.signatures)
print(json.dumps(kernels))
"""


def _loaded_kernels(warm: bool) -> dict[str, int]:
    done = subprocess.run(
        [sys.executable, "-c", _PROBE.format(warm=warm)],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    return json.loads(done.stdout.strip().splitlines()[-1])


def test_warm_up_loads_every_kernel_a_query_can_call():
    kernels = _loaded_kernels(warm=True)
    assert len(kernels) >= 6
    cold = [name for name, n_signatures in kernels.items() if n_signatures == 0]
    assert cold == [], f"kernels a first query would compile or load: {cold}"


def test_the_probe_sees_kernels_that_were_not_warmed():
    # Without the warm-up nothing is loaded: the check above can fail.
    assert all(n == 0 for n in _loaded_kernels(warm=False).values())


_QUERY_PROBE = """
import json
import numpy as np
from numba.core.registry import CPUDispatcher
from monoloc.core.camera import KITTI_CAM0 as CAM
from monoloc.core.geometry import T_world_from_cam_planar, invert_rigid
from monoloc.core.prior import RetrievalPrior
from monoloc.server.index import _scan_kernel
from monoloc.server.index.retrieval import IndexConfig, RetrievalIndex
from monoloc.server.index.warmup import warm_up as warm_up_index
from monoloc.server.localize import LocalizeConfig, ReferenceEntry, pose_hypotheses
from monoloc.server.vision import (
    _covariance_kernel, _hamming_kernel, _pnp_kernel, _vlad_kernel, _window_kernel,
)
from monoloc.server.vision.binary_code import vlad_binary_code
from monoloc.server.vision.matching import match_against_references
from monoloc.server.vision.warmup import warm_up as warm_up_vision

def signatures():
    out = {{}}
    for module in (
        _covariance_kernel, _hamming_kernel, _pnp_kernel, _scan_kernel, _vlad_kernel,
        _window_kernel,
    ):
        for name, obj in vars(module).items():
            if isinstance(obj, CPUDispatcher) and obj.__module__ == module.__name__:
                out[module.__name__ + "." + name] = len(obj.signatures)
    return out

warm_up_vision()
warm_up_index()
before = signatures()
rng = np.random.default_rng(0)
# Retrieval as a query runs it: the flat and the scan index, with and without a prior.
vlads = rng.normal(size=(40, 2048)).astype(np.float32)
vlads /= np.linalg.norm(vlads, axis=1, keepdims=True)
codes = np.stack([vlad_binary_code(v) for v in vlads])
poses = np.c_[np.arange(40.0), np.zeros(40), np.zeros(40)]
for config in (IndexConfig(), IndexConfig(scan_min_entries=10)):
    index = RetrievalIndex(config)
    index.add(np.arange(40), codes, vlads, poses)
    for prior in (None, RetrievalPrior(5.0, 0.0, 8.0, 0.0, 0.5)):
        index.search(vlads[3], codes[3], 10, prior)
# Matching and PnP as a query runs them: float32 keypoints, several entries (guided, joint).
T_world_from_query = T_world_from_cam_planar(10.0, 2.0, 0.3, 1.65)
depth = rng.uniform(6.0, 40.0, 300)
pixels = np.c_[rng.uniform(0, CAM.width_px - 1, 300), rng.uniform(0, CAM.height_px - 1, 300)]
points_query = np.c_[
    (pixels[:, 0] - CAM.cx) / CAM.fx * depth, (pixels[:, 1] - CAM.cy) / CAM.fy * depth, depth
]
descriptors = rng.integers(0, 256, (300, 32), dtype=np.uint8)
refs = []
for j in range(4):
    T_world_from_ref = T_world_from_cam_planar(10.0 + j, 2.0, 0.3, 1.65)
    T_ref_from_query = invert_rigid(T_world_from_ref) @ T_world_from_query
    R, t = T_ref_from_query[:3, :3], T_ref_from_query[:3, 3]
    points_ref = (points_query @ R.T + t).astype(np.float32)
    refs.append(ReferenceEntry(j, T_world_from_ref, descriptors.copy(), points_ref))
matches = match_against_references(descriptors, [r.descriptors for r in refs])
# as the localizer runs it (pose covariances weighed by keypoint scales, or without scales)
for scales in (np.ones(300), None):
    for prior in (None, RetrievalPrior(10.0, 2.0, 5.0, 0.3, 0.5)):
        hyps, _ = pose_hypotheses(
            pixels.astype(np.float32), refs, matches, {{j: 0.5 for j in range(4)}}, CAM,
            LocalizeConfig().poses, rng, prior=prior, keypoint_scales=scales,
            descriptors=descriptors,
        )
        assert len(hyps) == 5, len(hyps)
        assert all(h.covariance_px1 is not None for h in hyps)
after = signatures()
print(json.dumps({{k: [before[k], after[k]] for k in after}}))
"""


def test_a_query_after_the_warm_up_compiles_nothing():
    # Same types and layouts as a real query (float32 keypoints and points, guided PnP,
    # joint pose, pose covariances, prior or none, flat and scan index): no kernel gains a
    # signature, i.e.
    # nothing is compiled or loaded inside a query.
    done = subprocess.run(
        [sys.executable, "-c", _QUERY_PROBE.format()],
        capture_output=True,
        text=True,
        timeout=300,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    counts = json.loads(done.stdout.strip().splitlines()[-1])
    added = {name: n for name, n in counts.items() if n[1] != n[0]}
    assert added == {}, f"kernels compiled or loaded by a query after the warm-up: {added}"
