"""The operator's console (/ui) and the offline /docs in a real headless Chromium
(Debian's /usr/bin/chromium driven by Playwright; no browser download), against a real
uvicorn server started here with its own data folder and a small sim city (map run +
night images of the same street). Requests to any host but the server are aborted and
recorded, so every page is checked the way it runs in a depot without internet.

Screenshots of each page go to the test's tmp_path (printed with -s) for a reviewer."""

from __future__ import annotations

import json
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
from e2e_helpers import (
    ADMIN_KEY,
    camera_json,
    create_keys,
    live_server,
    make_settings,
    tar_sequence,
    upload_map_run,
)
from playwright import sync_api

CHROMIUM = Path("/usr/bin/chromium")
CITY_FRAMES = 12
NIGHT_COLOUR = "#6a3d9a"  # console.js TAG_COLOURS.night


@pytest.fixture(scope="module")
def city(tmp_path_factory) -> dict:
    """A map run and a night run of the same street (nightmap: lane centre, at night)."""
    from monoloc.sim.generate import GenerateConfig, generate_dataset
    from monoloc.sim.lidar import LidarConfig

    root = tmp_path_factory.mktemp("console_city")
    config = GenerateConfig(
        runs=("map", "nightmap"),
        max_frames=CITY_FRAMES,
        lidar=LidarConfig(azimuth_steps=1000),
        seed=0,
    )
    generate_dataset(config, root)
    described = json.loads((root / "dataset.json").read_text())
    seqs = {s["run"]: s["id"] for s in described["sequences"]}
    return {"root": root, "map": seqs["map"], "night": seqs["nightmap"]}


@pytest.fixture(scope="module")
def server(city, tmp_path_factory):
    """A live server with map 'street' (the map run) and a localize and a map:write key."""
    from monoloc.client.api import MonolocClient

    data_dir = tmp_path_factory.mktemp("console_server") / "data"
    with live_server(make_settings(data_dir)) as (url, app):
        with MonolocClient(url, ADMIN_KEY, timeout_s=60.0) as admin:
            keys = create_keys(admin)
            map_id = upload_map_run(admin, "street", city["root"], city["map"])
            yield {"url": url, "app": app, "map_id": map_id, "keys": keys, "admin": admin}


@pytest.fixture(scope="module")
def browser():
    with sync_api.sync_playwright() as playwright:
        chromium = playwright.chromium.launch(
            executable_path=str(CHROMIUM),
            headless=True,
            args=[
                "--no-sandbox",
                "--disable-background-networking",
                "--disable-component-update",
                "--disable-default-apps",
                "--disable-sync",
                "--no-first-run",
            ],
        )
        try:
            yield chromium
        finally:
            chromium.close()


class Offline:
    """A browser page whose requests to anything but the server are aborted (recorded)."""

    def __init__(self, browser, base_url: str, out: Path) -> None:
        self.base_url, self.out, self.blocked = base_url, out, []
        self.tolerated: set[str] = set()
        self.context = browser.new_context(viewport={"width": 1400, "height": 950})
        self.context.route("**/*", self._route)
        self.page = self.context.new_page()
        self.page.set_default_timeout(60_000)
        self.errors: list[str] = []
        self.page.on("pageerror", lambda exc: self.errors.append(str(exc)))

    def _route(self, route) -> None:
        if route.request.url.startswith(self.base_url):
            route.continue_()
        else:
            self.blocked.append(route.request.url)
            route.abort()

    def shot(self, name: str) -> Path:
        path = self.out / f"{name}.png"
        self.page.screenshot(path=str(path), full_page=True)
        return path

    def sign_in(self, key: str) -> None:
        self.page.goto(f"{self.base_url}/ui#/signin")
        self.page.fill("#key", key)
        self.page.click("#signin")

    def close(self) -> None:
        self.context.close()


@pytest.fixture
def offline(browser, server, tmp_path):
    out = tmp_path / "screenshots"
    out.mkdir()
    tab = Offline(browser, server["url"], out)
    yield tab
    tab.close()
    print(f"\nscreenshots: {out}")
    assert not tab.errors, f"script errors in the page: {tab.errors}"
    reached_out = [u for u in tab.blocked if u not in tab.tolerated]
    assert not reached_out, f"the page reached out of the server: {reached_out}"


def _api(server, method: str, path: str, **kwargs):
    return server["admin"].request(method, path, **kwargs).json()


def test_docs_list_every_route_with_the_network_off(offline, server):
    spec = _api(server, "GET", "/openapi.json")
    n_operations = sum(
        method in ("get", "post", "put", "patch", "delete")
        for item in spec["paths"].values()
        for method in item
    )
    page = offline.page
    page.goto(f"{server['url']}/docs")
    page.wait_for_function(
        "n => document.querySelectorAll('.opblock').length === n", arg=n_operations
    )
    assert page.locator(".opblock-summary-path", has_text="/v1/maps/{map_id}/localize").count()
    offline.shot("docs")
    # ReDoc's bundle hard-codes its maker's logo (an <img> it hides when it fails to load)
    offline.tolerated.add("https://cdn.redoc.ly/redoc/logo-mini.svg")
    page.goto(f"{server['url']}/redoc")
    page.locator("h2", has_text="Create a map").first.wait_for()
    offline.shot("redoc")


@pytest.mark.parametrize(
    ("which", "scope", "visible", "hidden"),
    [
        ("localize", "localize", ["Maps"], ["Jobs"]),
        ("write", "map:write", ["Maps", "Jobs"], []),
        ("admin", "admin", ["Maps", "Jobs"], []),
    ],
)
def test_sign_in_with_each_scope(offline, server, which, scope, visible, hidden):
    page = offline.page
    offline.sign_in(getattr(server["keys"], which))
    page.wait_for_function("s => document.querySelector('#who').dataset.scope === s", arg=scope)
    for name in visible:
        assert page.locator("#nav a", has_text=name).is_visible()
    for name in hidden:
        assert not page.locator("#nav a", has_text=name).is_visible()
    # every key sees the maps (a vehicle key and a mapping team's map:write key alike)
    row = page.locator(f"#maps tr[data-map-id='{server['map_id']}']")
    n_entries = _api(server, "GET", f"/v1/maps/{server['map_id']}")["n_entries"]
    assert row.locator(".n-entries").inner_text() == str(n_entries)
    # ... and the map's page; map:write and admin also get its editing links
    page.goto(f"{server['url']}/ui#/maps/{server['map_id']}")
    page.locator("h1", has_text="Map ").wait_for()
    page.locator("#map-plot .main-svg").first.wait_for()
    assert page.locator("#add-link").count() == (0 if which == "localize" else 1)
    if which == "localize":  # an editing page says why it is closed
        page.goto(f"{server['url']}/ui#/jobs")
        assert "map:write" in page.locator("#page-error").inner_text()
    offline.shot(f"signed-in-{which}")
    # the key lives in this tab's session storage; signing out forgets it
    assert page.evaluate("sessionStorage.getItem('monoloc.apiKey')") == getattr(
        server["keys"], which
    )
    page.click("#signout")
    page.locator("#key").wait_for()
    assert page.evaluate("sessionStorage.getItem('monoloc.apiKey')") is None


def test_a_wrong_key_is_refused(offline, server):
    offline.sign_in("mlk_" + "x" * 43)
    error = offline.page.locator("#signin-error")
    error.filter(has_text="refused").wait_for()
    assert "unknown or revoked" in error.inner_text()
    assert offline.page.locator("#nav").is_hidden()


def _wait_plot_entries(page, n: int) -> None:
    """Wait until the map plot shows ``n`` entries (the page sets data-entries)."""
    page.wait_for_function(
        "n => { const p = document.querySelector('#map-plot');"
        " return p !== null && p.dataset.entries === String(n); }",
        arg=n,
    )


def _plot_entries(page, selector: str = "#map-plot") -> dict[str, list[int]]:
    """Entry ids per tag trace of a Plotly plot, read from the page."""
    return page.evaluate(
        """sel => Object.fromEntries(document.querySelector(sel).data
             .filter(t => t.meta && t.meta.tag)
             .map(t => [t.meta.tag, {ids: t.customdata, colour: t.marker.color}]))""",
        selector,
    )


def _night_frame(city) -> dict:
    from monoloc.server.ingest.sources import read_kitti_sequence

    seq = read_kitti_sequence(city["root"], city["night"])
    frame = seq.frames[CITY_FRAMES // 2]
    return {
        "image": frame.image_path,
        "scan": frame.scan_path,
        "T": ",".join(f"{v:.10g}" for v in frame.T_world_from_cam.reshape(-1)),
        "T_lidar": ",".join(f"{v:.10g}" for v in seq.T_cam_from_lidar.reshape(-1)),
        "xy": frame.T_world_from_cam[:2, 3],
        "t": float(frame.timestamp_s),
    }


def test_map_plot_night_upload_and_entry_page(offline, server, city, tmp_path):
    page, url, map_id = offline.page, server["url"], server["map_id"]
    before = _api(server, "GET", f"/v1/maps/{map_id}")["n_entries"]
    offline.sign_in(ADMIN_KEY)
    page.locator("#maps").wait_for()
    page.goto(f"{url}/ui#/maps/{map_id}")
    _wait_plot_entries(page, before)
    traces = _plot_entries(page)
    assert list(traces) == ["day"] and len(traces["day"]["ids"]) == before
    offline.shot("map")

    # add one night image (with its LiDAR scan) through the add-images page
    night = _night_frame(city)
    page.goto(f"{url}/ui#/maps/{map_id}/add")
    page.set_input_files("#images", str(night["image"]))
    scan = tmp_path / (night["image"].stem + ".bin")
    shutil.copy(night["scan"], scan)
    page.set_input_files("#sources", str(scan))
    page.fill("#poses", night["T"])
    page.fill("#lidar-T", night["T_lidar"])
    page.fill("#timestamps", f"{night['t']:.6f}")
    page.click("#upload")
    outcome = page.locator("#add-results .outcome").first
    outcome.filter(has_text="added").wait_for()
    new_id = int(outcome.inner_text().split("entry ")[1].split(",")[0])
    offline.shot("add-images")

    page.goto(f"{url}/ui#/maps/{map_id}")
    _wait_plot_entries(page, before + 1)
    traces = _plot_entries(page)
    assert traces["night"] == {"ids": [new_id], "colour": NIGHT_COLOUR}
    assert new_id not in traces["day"]["ids"]
    # the night entry sits where the image was taken
    xy = page.evaluate(
        "() => { const t = document.querySelector('#map-plot').data"
        ".find(t => t.meta && t.meta.tag === 'night'); return [t.x[0], t.y[0]]; }"
    )
    np.testing.assert_allclose(xy, night["xy"], atol=1e-6)
    # the filter by tag keeps the night entry only; the gaps are then the rest of the route
    page.select_option("#filter-tag", "night")
    _wait_plot_entries(page, 1)
    gaps = page.evaluate(
        "document.querySelector('#map-plot').data.find(t => t.meta && 'gaps' in t.meta).meta.gaps"
    )
    assert gaps >= 1
    offline.shot("map-night-only")

    # the entry page: keypoints, pose, re-tag, delete after a confirmation
    page.goto(f"{url}/ui#/maps/{map_id}/entries/{new_id}")
    page.locator("#keypoint-plot .main-svg").first.wait_for()
    n_points = _api(server, "GET", f"/v1/maps/{map_id}/entries/{new_id}")["n_points"]
    plotted = page.evaluate(
        "Object.fromEntries(document.querySelector('#keypoint-plot').data"
        ".map(t => [t.meta ? t.meta.kind : t.type, t.type === 'image' ? "
        "[t.source.slice(0, 23), t.dx, t.dy] : t.x.length]))"
    )
    # the image is shown (a JPEG the server kept), scaled to full-size pixels, with the
    # keypoints that have a 3D point and those that have none
    assert plotted["with"] == n_points > 0 and plotted["without"] > 0
    source, dx, dy = plotted["image"]
    assert source == "data:image/jpeg;base64,"
    assert dx == pytest.approx(1241 / 640) and dy == pytest.approx(376 / 194)
    entry = _api(server, "GET", f"/v1/maps/{map_id}/entries/{new_id}")
    assert entry["timestamp_s"] == pytest.approx(night["t"])
    offline.shot("entry")
    page.fill("#tags", "night, off-center")
    page.click("#retag")
    page.locator("#entry-outcome", has_text="tags saved").wait_for()
    assert _api(server, "GET", f"/v1/maps/{map_id}/entries/{new_id}")["tags"] == [
        "night",
        "off-center",
    ]
    page.once("dialog", lambda dialog: dialog.dismiss())
    page.click("#delete")
    page.locator("#entry-outcome", has_text="not deleted").wait_for()
    assert _api(server, "GET", f"/v1/maps/{map_id}")["n_entries"] == before + 1
    page.once("dialog", lambda dialog: dialog.accept())
    page.click("#delete")
    _wait_plot_entries(page, before)
    assert _api(server, "GET", f"/v1/maps/{map_id}")["n_entries"] == before


def test_jobs_page_watches_an_ingestion_reach_100(offline, server, city):
    from monoloc.core.camera import KITTI_CAM0

    page = offline.page
    offline.sign_in(server["keys"].write)
    page.locator("#maps").wait_for()  # every key lands on the maps
    page.goto(f"{server['url']}/ui#/jobs")
    page.locator("#jobs").wait_for()
    camera = camera_json(KITTI_CAM0)
    made = _api(server, "POST", "/v1/maps", json={"name": "night", "camera": camera})
    accepted = _api(
        server,
        "POST",
        f"/v1/maps/{made['id']}/runs",
        files={"archive": ("night.tar.gz", tar_sequence(city["root"], city["night"]), "x")},
        data={"format": "kitti", "kind": "map"},
    )
    job_id = accepted["job"]["id"]
    row = page.locator(f"#jobs tr[data-job-id='{job_id}']")
    row.wait_for()
    seen = set()
    deadline = time.monotonic() + 120
    while time.monotonic() < deadline:
        # one read of both attributes per look: reading the state a second time for the
        # exit test could see a refresh the recorded pair did not (it once broke on
        # "done" having recorded only ("running", "0"))
        state, progress = row.evaluate("r => [r.dataset.state, r.dataset.progress]")
        seen.add((state, progress))
        if state == "done":
            break
        time.sleep(0.1)
    assert ("done", "100") in seen, seen
    assert "100 %" in row.inner_text()
    offline.shot("jobs")


def test_jobs_page_cancels_a_queued_job_and_resumes_it(offline, server, city):
    """One job runs at a time (job_threads=1): the last of four submitted ingestions waits
    queued behind the others, long enough to be cancelled from the page; it ends
    interrupted with nothing of it in the map, and its resume button takes it to done."""
    from monoloc.core.camera import KITTI_CAM0

    page = offline.page
    offline.sign_in(server["keys"].write)
    page.locator("#maps").wait_for()  # every key lands on the maps
    page.goto(f"{server['url']}/ui#/jobs")
    page.locator("#jobs").wait_for()
    archive = tar_sequence(city["root"], city["night"])
    jobs = []
    for i in range(4):
        made = _api(
            server,
            "POST",
            "/v1/maps",
            json={"name": f"queue{i}", "camera": camera_json(KITTI_CAM0)},
        )
        accepted = _api(
            server,
            "POST",
            f"/v1/maps/{made['id']}/runs",
            files={"archive": ("night.tar.gz", archive, "x")},
            data={"format": "kitti", "kind": "map"},
        )
        jobs.append((made["id"], accepted["job"]["id"]))
    last_map, last_job = jobs[-1]
    row = page.locator(f"#jobs tr[data-job-id='{last_job}']")
    row.locator("button.cancel").click()
    page.locator(f"#jobs tr[data-job-id='{last_job}'][data-state='interrupted']").wait_for()
    assert "cancelled" in row.inner_text()
    offline.shot("jobs-cancelled")
    assert _api(server, "GET", f"/v1/jobs/{last_job}")["state"] == "interrupted"
    for _map_id, job_id in jobs[:-1]:  # the others are not disturbed
        page.locator(f"#jobs tr[data-job-id='{job_id}'][data-state='done']").wait_for(
            timeout=120_000
        )
    assert _api(server, "GET", f"/v1/maps/{last_map}")["n_entries"] == 0

    row.locator("button.resume").click()
    page.locator(f"#jobs tr[data-job-id='{last_job}'][data-state='done']").wait_for(timeout=120_000)
    assert "100 %" in row.inner_text()
    offline.shot("jobs-resumed")
    n_first = _api(server, "GET", f"/v1/maps/{jobs[0][0]}")["n_entries"]
    assert _api(server, "GET", f"/v1/maps/{last_map}")["n_entries"] == n_first > 0


def test_live_page_follows_a_vehicle(offline, server, city):
    from monoloc.client.api import FrameStream
    from monoloc.server.ingest.sources import read_kitti_sequence

    page, url, map_id = offline.page, server["url"], server["map_id"]
    offline.sign_in(server["keys"].localize)
    page.locator("#maps").wait_for()
    page.goto(f"{url}/ui#/maps/{map_id}/live")
    page.locator("#vehicles").wait_for()
    seq = read_kitti_sequence(city["root"], city["map"])
    stream = FrameStream(url, server["keys"].localize, map_id, timeout_s=60)
    seen = []
    try:
        for i, frame in enumerate(seq.frames[1:9:2]):
            stream.send(i, frame.timestamp_s, frame.image_path.read_bytes())
            answer = stream.receive()
            assert answer["hypotheses"], answer
            # the page draws the vehicle's estimate for this frame
            xy = page.evaluate_handle(
                """seq => new Promise(resolve => { const check = () => {
                     const t = (document.querySelector('#live-plot').data || [])
                       .find(t => t.meta && t.meta.seq === seq);
                     t ? resolve([t.x[0], t.y[0]]) : setTimeout(check, 50); }; check(); })""",
                i,
            ).json_value()
            seen.append(xy)
            np.testing.assert_allclose(xy, frame.T_world_from_cam[:2, 3], atol=1.0)
        row = page.locator("#vehicles tr[data-vehicle-id]")
        assert row.get_attribute("data-frames") == "4"
        assert float(row.locator(".rate").inner_text().split()[0]) > 0
        offline.shot("live")
    finally:
        stream.close()
    steps = np.linalg.norm(np.diff(np.asarray(seen), axis=0), axis=1)
    assert (steps > 0.5).all(), seen  # it moved on the page, frame after frame


def test_maps_page_names_the_calibrated_conditions(offline, server):
    """A map whose calibration has a night condition reads "calibrated (+night)" on the
    maps page and its own page; back to "defaults" once the calibration is deleted."""
    page, url, map_id = offline.page, server["url"], server["map_id"]
    model = dict(
        mu1=[0.0, 0.0, 0.0],
        Sigma1=np.diag([0.04, 0.04, 0.0007]).tolist(),
        mu2=[0.9, 0.0, 0.0, 0.0],
        Sigma2=np.diag([0.06, 64.0, 64.0, 0.27]).tolist(),
    )
    put = server["admin"].request(
        "PUT", f"/v1/maps/{map_id}/calibration", json=dict(model, conditions={"night": model})
    )
    assert put.status_code == 200, put.text
    try:
        offline.sign_in(ADMIN_KEY)
        cell = page.locator(f'#maps tr[data-map-id="{map_id}"] td').nth(5)
        cell.wait_for()
        assert cell.inner_text() == "calibrated (+night)"
        page.goto(f"{url}/ui#/maps/{map_id}")
        page.get_by_text("calibrated (+night)").wait_for()
    finally:
        server["admin"].request("DELETE", f"/v1/maps/{map_id}/calibration")
    page.goto(f"{url}/ui#/maps")
    page.reload()
    cell = page.locator(f'#maps tr[data-map-id="{map_id}"] td').nth(5)
    cell.wait_for()
    assert cell.inner_text() == "defaults"
