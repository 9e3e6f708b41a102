"""The demo path end to end on a tiny city: sim -> server -> vocabulary, calibration,
map upload -> WebSocket drives with the filter -> table and plots."""

import json

import cv2
import pytest
from busy_machine import generous_env

from monoloc.demo import DemoConfig, run_demo


@pytest.fixture(scope="module")
def demo_summary(tmp_path_factory):
    out = tmp_path_factory.mktemp("demo")
    _leave_a_previous_runs_server(out / "server")
    # The closed-loop lap is left out here: its steps have their own end-to-end test
    # (test_e2e_closed_loop.py), and it would add ~40 s to this one.
    config = DemoConfig(out_dir=out, frames=40, seed=5, closed_loop_frames=0)
    with pytest.MonkeyPatch.context() as env:  # the demo's `monoloc serve` reads them
        for name, value in generous_env().items():
            env.setenv(name, value)
        return run_demo(config), out


def _leave_a_previous_runs_server(data_dir):
    """What an earlier `make demo` leaves in out/demo/server: a database whose admin key
    is that run's (each run makes a new one). A second run must still work."""
    from monoloc.local_server import new_admin_key
    from monoloc.server.api.bootstrap import bootstrap_admin_key
    from monoloc.server.settings import Settings
    from monoloc.server.storage.db import create_engine_for, make_session_factory
    from monoloc.server.storage.migrate import upgrade_database

    settings = Settings(data_dir=data_dir, bootstrap_admin_key=new_admin_key())
    upgrade_database(settings.database_url)
    engine = create_engine_for(settings)
    try:
        assert bootstrap_admin_key(make_session_factory(engine), settings)
    finally:
        engine.dispose()


def test_demo_localizes_the_query_run(demo_summary):
    summary, out = demo_summary
    query = summary["runs"]["query"]["metrics"]
    # every frame of the query run, which stops where the map run's stretch ends
    (meta,) = out.glob("city_*/dataset.json")
    frames = {s["run"]: s["frames"] for s in json.loads(meta.read_text())["sequences"]}
    assert query["n_frames"] == frames["query"] and 20 <= frames["query"] <= 40
    assert query["coverage"] >= 0.9
    assert query["position_rmse_m"] < 0.5
    assert json.loads((out / "summary.json").read_text())["map_id"] == summary["map_id"]
    # The night run was driven before and after the operator added night images.
    assert len(summary["runs"]) == 3


def test_demo_plots_are_real_images(demo_summary):
    summary, _ = demo_summary
    assert len(summary["plots"]) == 3
    for path in summary["plots"]:
        image = cv2.imread(path)
        assert image is not None and image.shape[0] > 200 and image.shape[1] > 300
        assert image.std() > 5  # not a blank canvas
