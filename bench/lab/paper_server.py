"""`monoloc serve` running the paper-faithful pipeline (bench.lab.paper), for benchmarks
that compare it with the product through the real server (bench/speed.py):

    python -m bench.lab.paper_server serve --port 8001 ...

The lab's one seam into the server process: every frame the map registry localizes goes
through ``PAPER_STAGES`` instead of the product's stages. One process only (uvicorn's
own workers would not inherit the seam). The product has no setting for it."""

from __future__ import annotations

import functools


def use_paper_stages() -> None:
    """Make every ``MapRegistry.localize`` of this process run ``PAPER_STAGES``."""
    from bench.lab.paper import PAPER_STAGES
    from monoloc.server.map_registry import MapRegistry

    product = MapRegistry.localize

    @functools.wraps(product)
    def localize(self, *args, **kwargs):
        kwargs["stages"] = PAPER_STAGES
        return product(self, *args, **kwargs)

    MapRegistry.localize = localize


def main() -> None:
    from monoloc.cli import main as monoloc_main

    use_paper_stages()
    monoloc_main()


if __name__ == "__main__":
    main()
