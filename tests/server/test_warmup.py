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
from monoloc.server.index import _scan_kernel
from monoloc.server.vision import _hamming_kernel, _pnp_kernel
from monoloc.server.index.warmup import warm_up as warm_up_index
from monoloc.server.vision.warmup import warm_up as warm_up_vision

WARM = {warm}
if WARM:
    warm_up_vision()
    warm_up_index()
kernels = {{}}
for module in (_hamming_kernel, _pnp_kernel, _scan_kernel):
    for name, obj in vars(module).items():
        if isinstance(obj, CPUDispatcher) and obj.__module__ == module.__name__:
            if obj.targetoptions.get("inline") == "always":
                continue  # inlined into its callers, never called on its own
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
