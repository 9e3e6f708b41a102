"""docker/compose.yaml and docker/nginx.conf (Docker cannot run here): the compose file's
shape (PostgreSQL, migrations once, two replicas sharing uploads, nginx in front) and
nginx's own syntax check of the config (`nginx -t`, upstreams on loopback)."""

from __future__ import annotations

import subprocess

import pytest
import yaml
from fleet_helpers import REPO, find_nginx, loopback_nginx_conf


def _compose() -> dict:
    return yaml.safe_load((REPO / "docker" / "compose.yaml").read_text())


def test_compose_runs_postgres_migrations_once_two_replicas_and_nginx():
    services = _compose()["services"]
    assert {"postgres", "migrate", "monoloc-1", "monoloc-2", "nginx"} <= set(services)
    assert services["migrate"]["command"][-2:] == ["db", "upgrade"]
    assert services["migrate"]["depends_on"]["postgres"]["condition"] == "service_healthy"
    replicas = [services["monoloc-1"], services["monoloc-2"]]
    for replica in replicas:
        env = replica["environment"]
        assert env["MONOLOC_DATABASE_URL"].startswith("postgresql+psycopg://")
        assert "@postgres:5432/" in env["MONOLOC_DATABASE_URL"]
        assert env["MONOLOC_SKIP_MIGRATIONS"] == "1"  # the migrate service did it, once
        assert replica["depends_on"]["migrate"]["condition"] == "service_completed_successfully"
        assert "shared:/shared" in replica["volumes"]
        assert env["MONOLOC_UPLOADS_DIR"].startswith("/shared/")
    data = [v for r in replicas for v in r["volumes"] if v.endswith(":/data")]
    assert len(set(data)) == 2  # each replica its own data directory
    assert "./nginx.conf:/etc/nginx/nginx.conf:ro" in services["nginx"]["volumes"]
    conf = (REPO / "docker" / "nginx.conf").read_text()
    assert "server monoloc-1:8000" in conf and "server monoloc-2:8000" in conf
    start = (REPO / "docker" / "start.sh").read_text()
    assert "MONOLOC_SKIP_MIGRATIONS" in start


def test_nginx_accepts_the_config(tmp_path):
    nginx = find_nginx()
    if nginx is None:
        pytest.fail("nginx is not installed (make test installs Debian's nginx-light)")
    for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"):
        (tmp_path / kind).mkdir()
    conf = loopback_nginx_conf(tmp_path, [18001, 18002], 18000)
    done = subprocess.run(
        [nginx, "-t", "-p", str(tmp_path), "-c", str(conf)], capture_output=True, text=True
    )
    assert done.returncode == 0, done.stderr
    assert "syntax is ok" in done.stderr


def test_nginx_starts_again_after_it_was_killed(tmp_path):
    """docker/compose.yaml restarts a dead nginx in the same container: nothing a killed
    nginx leaves behind (its admission server's listener included) may stop the next."""
    import os
    import signal
    import socket
    import time

    nginx = find_nginx()
    if nginx is None:
        pytest.fail("nginx is not installed (make test installs Debian's nginx-light)")
    for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"):
        (tmp_path / kind).mkdir()
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        port = sock.getsockname()[1]
    conf = loopback_nginx_conf(tmp_path, [18001, 18002], port)
    command = [nginx, "-p", str(tmp_path), "-c", str(conf), "-g", "daemon off;"]
    for _attempt in range(2):
        master = subprocess.Popen(command, stderr=subprocess.PIPE)
        deadline = time.monotonic() + 10
        while True:
            assert master.poll() is None, master.stderr.read().decode()
            try:
                socket.create_connection(("127.0.0.1", port), 0.2).close()
                break
            except OSError:
                assert time.monotonic() < deadline, "nginx did not listen"
                time.sleep(0.05)
        children = open(f"/proc/{master.pid}/task/{master.pid}/children").read().split()
        for pid in [master.pid, *map(int, children)]:  # SIGKILL: no clean-up at all
            os.kill(pid, signal.SIGKILL)
        master.wait(10)
        time.sleep(0.2)


def test_a_frame_no_replica_can_take_is_a_502_when_none_is_up(tmp_path):
    """nginx's localize admission answers a frame it cannot place: 503 "overloaded" when
    no replica has room (tests/fleet/test_replicas.py), and a 502 in the same JSON shape,
    with no Retry-After promise, when no replica can be reached at all."""
    import socket
    import time

    import httpx

    nginx = find_nginx()
    if nginx is None:
        pytest.fail("nginx is not installed (make test installs Debian's nginx-light)")
    for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"):
        (tmp_path / kind).mkdir()
    ports = []
    for _ in range(3):  # nothing listens on the replicas' ports
        with socket.socket() as sock:
            sock.bind(("127.0.0.1", 0))
            ports.append(sock.getsockname()[1])
    conf = loopback_nginx_conf(tmp_path, ports[:2], ports[2])
    master = subprocess.Popen([nginx, "-p", str(tmp_path), "-c", str(conf), "-g", "daemon off;"])
    try:
        deadline = time.monotonic() + 10
        while True:
            try:
                socket.create_connection(("127.0.0.1", ports[2]), 0.2).close()
                break
            except OSError:
                assert master.poll() is None and time.monotonic() < deadline, "no nginx"
                time.sleep(0.05)
        answer = httpx.post(
            f"http://127.0.0.1:{ports[2]}/v1/maps/1/localize",
            files={"image": ("f.png", b"\x89PNG\r\n\x1a\n" + bytes(1000), "image/png")},
            timeout=10,
        )
    finally:
        master.terminate()
        master.wait(10)
    assert answer.status_code == 502, answer.text
    assert answer.json()["error"]["code"] == "bad_gateway"
    assert "retry-after" not in answer.headers
    log = (tmp_path / "access.log").read_text()
    assert f"upstream=127.0.0.1:{ports[0]}, 127.0.0.1:{ports[1]} " in log or (
        f"upstream=127.0.0.1:{ports[1]}, 127.0.0.1:{ports[0]} " in log
    ), log  # both were tried
