"""Issue 52's shard test on loopback: two shard groups x two `monoloc serve` replicas
behind the nginx router, each group on its own PostgreSQL with PostGIS (group 'west' a
single server, group 'east' a pg_auto_failover formation: monitor, primary, secondary;
its replicas hold the multi-host URL with target_session_attrs=read-write). A vehicle
drives the query run across the tile border with one filter (ShardedLocalizer); mid-drive
one replica of 'west' is SIGKILLed and 'east' fails over (`pg_autoctl perform failover`).
Every frame is answered (none dropped, none refused, nginx answered no 5xx), the
failover happened while the drive went on, and the drive's RMSE against the sim's truth
is stated."""

from __future__ import annotations

import re
import threading
import time

import numpy as np
import pytest
from fleet_helpers import ADMIN_KEY, Replica, free_port, replica_env
from pg_cluster import fresh_database
from pg_formation import start_formation
from shard_helpers import GROUPS, start_router, stop_process

from monoloc.client.drive import DriveConfig, drive_with
from monoloc.client.particle_filter import FilterConfig
from monoloc.client.replay import read_run
from monoloc.client.sharded import ShardedLocalizer
from monoloc.core.tiles import ShardGroup

pytestmark = pytest.mark.slow

KILL_AT = 6  # frame after which west's first replica is SIGKILLed
FAILOVER_AT = 10  # frame after which east's PostgreSQL fails over
FRAME_PERIOD_S = 0.25  # the drive's pace: the failover (~5 s) spans many frames


def test_a_drive_across_the_border_survives_a_killed_replica_and_a_failover(
    split_street, postgres_admin_url, tmp_path
):
    formation = start_formation((free_port(), free_port(), free_port()))
    if formation is None:
        pytest.fail("pg_autoctl is not installed (make system-deps installs it)")
    replicas: dict[str, list[Replica]] = {}
    router = None
    try:
        with fresh_database(postgres_admin_url) as west_url:
            urls = {"west": west_url, "east": formation.url}
            for group in GROUPS:
                split_street.ingest_half(urls[group], group)
                env = replica_env(urls[group], tmp_path / group / "uploads")
                replicas[group] = [
                    Replica(f"{group}-{i}", free_port(), tmp_path / group / f"r{i}", env)
                    for i in (1, 2)
                ]
            everyone = [r for group in GROUPS for r in replicas[group]]
            for replica in everyone:
                replica.start()
            for replica in everyone:
                replica.wait_ready()
            groups = {
                g: ShardGroup(g, None, tuple(f"127.0.0.1:{r.port}" for r in replicas[g]))
                for g in GROUPS
            }
            port = free_port()
            table = split_street.table(groups, router=f"http://127.0.0.1:{port}")
            router = start_router(tmp_path, table, port)
            _drive_and_check(split_street, table, replicas, formation, tmp_path)
    finally:
        stop_process(router)
        for replica in (r for group in replicas.values() for r in group):
            replica.stop()
        formation.stop()


def _drive_and_check(split_street, table, replicas, formation, tmp_path) -> None:
    run = read_run(split_street.root, "01")
    primary_before = formation.primary_port()
    events: dict[str, float] = {}
    failover_errors: list[BaseException] = []

    def failover() -> None:
        events["failover_start"] = time.monotonic()
        try:
            formation.failover()
        except BaseException as exc:  # noqa: BLE001 - reported on the test's thread
            failover_errors.append(exc)
        events["failover_end"] = time.monotonic()

    thread = threading.Thread(target=failover)
    sent_at: list[float] = []

    def progress(done: int, total: int) -> None:
        sent_at.append(time.monotonic())
        if done == KILL_AT:
            replicas["west"][0].kill()
            events["kill"] = time.monotonic()
        if done == FAILOVER_AT:
            thread.start()
        time.sleep(FRAME_PERIOD_S)

    with ShardedLocalizer.connect(table, ADMIN_KEY, run.intrinsics) as localizer:
        model, _ = localizer.measurement_model()
        config = DriveConfig(filter=FilterConfig(n_particles=500))
        result = drive_with(localizer, run, model, config, progress=progress)
        counts, routes, failures = localizer.counts, localizer.routes, localizer.last_errors
    thread.join(120)
    assert not failover_errors, failover_errors
    primary_after = formation.primary_port()

    for replica in replicas["east"]:  # shown when an assertion below fails
        print(f"--- {replica.name}'s log:\n{replica.log.read_text()[-2000:]}")
    m = result.metrics
    print(
        f"sharded drive, {len(run)} frames: position RMSE {m.position_rmse_m:.3f} m, heading "
        f"{m.heading_rmse_deg:.2f} deg; routes {routes}; per group {counts}; failover "
        f"{events['failover_end'] - events['failover_start']:.1f} s "
        f"(primary {primary_before} -> {primary_after})"
    )
    # every frame answered: none dropped, none refused, every group's request answered
    assert result.errors == {}, result.errors
    assert not result.dropped.any(), np.flatnonzero(result.dropped)
    for group in GROUPS:
        assert counts[group]["failed"] == counts[group]["shed"] == 0, (counts, failures)
        assert counts[group]["answered"] == counts[group]["sent"] > 0, counts
    assert routes["several_groups"] > 0 and routes["one_group"] > 0, routes
    assert m.position_rmse_m < 0.5, m
    # the failover happened, and frames went to east while it did
    assert primary_after != primary_before
    during = [t for t in sent_at if events["failover_start"] <= t <= events["failover_end"] + 1.0]
    assert len(during) >= 3, (events, len(sent_at))
    # nginx answered every request itself without a 5xx, and tried the killed replica
    # (then the other one) after the kill
    log = (tmp_path / "access.log").read_text().splitlines()
    statuses = [int(re.search(r'" (\d{3}) ', line).group(1)) for line in log]
    assert statuses and max(statuses) < 500, [line for line in log if '" 5' in line]
    killed = f"127.0.0.1:{replicas['west'][0].port}"
    retried = [line for line in log if killed in line and "upstream=" in line and ", " in line]
    print(f"requests nginx passed on from the killed replica: {len(retried)}")
    assert retried, "nginx never tried the killed replica: the kill was not on the path"
