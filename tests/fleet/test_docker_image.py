"""What docker/ deploys, as far as this machine can run it (no images can be pulled or
built here): the image's requirement set installed into a fresh venv from the files the
Dockerfile copies migrates a real PostgreSQL through the compose file's driver; the
volumes the compose file writes to are the image user's; and start.sh's steps (migrate
once, then replicas with the compose file's environment) behind docker/nginx.conf on
loopback localize a frame and pass the console's live events through unbuffered."""

from __future__ import annotations

import os
import re
import shutil
import subprocess
import sys
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import httpx
import pytest
import yaml
from busy_machine import generous_env
from fleet_helpers import (
    ADMIN_KEY,
    REPO,
    create_map,
    find_nginx,
    free_port,
    loopback_nginx_conf,
    upload_run,
    wait_job,
)

DOCKER = REPO / "docker"


def _compose() -> dict:
    return yaml.safe_load((DOCKER / "compose.yaml").read_text())


def _replica_environment() -> dict[str, str]:
    return {k: str(v) for k, v in _compose()["services"]["monoloc-1"]["environment"].items()}


def _dockerfile_lines() -> list[str]:
    """The Dockerfile's instructions, continuation lines joined."""
    return (DOCKER / "Dockerfile").read_text().replace("\\\n", " ").splitlines()


def _pip_target() -> str:
    """What the image's `pip install` installs, e.g. ``.[server,postgres]``."""
    for line in _dockerfile_lines():
        found = re.search(r"pip install '?(\.\[[^\]']*\])'?", line)
        if line.startswith("RUN") and found:
            return found.group(1)
    raise AssertionError("the Dockerfile installs no '.[extras]'")


def _build_context(tmp: Path) -> Path:
    """The files the Dockerfile COPYs into /app, copied under ``tmp``."""
    context = tmp / "app"
    context.mkdir()
    for line in _dockerfile_lines():
        parts = line.split()
        if not parts or parts[0] != "COPY" or parts[-1].startswith("/"):
            continue
        sources, dest = parts[1:-1], parts[-1]
        for source in sources:
            src = REPO / source
            target = context / dest / src.name if dest in ("./", ".") else context / dest
            if src.is_dir():
                ignore = shutil.ignore_patterns("__pycache__", "*.pyc")
                shutil.copytree(src, target, ignore=ignore)
            else:
                shutil.copy2(src, target)
    return context


# A fresh venv installs the image's requirement set (~60 s of pip): run by `make bench`;
# the compose and start.sh tests below keep the image's layout in `make test`.
@pytest.mark.slow
def test_the_image_requirement_set_migrates_postgres_in_a_fresh_venv(postgres_admin_url, tmp_path):
    """The compose file's migrate service, with the image's requirement set alone: it
    failed with "No module named 'psycopg'" when the image installed `.[server]`."""
    from pg_cluster import fresh_database
    from sqlalchemy import create_engine, inspect
    from sqlalchemy.engine import make_url

    compose_driver = _replica_environment()["MONOLOC_DATABASE_URL"].split("://")[0]
    context = _build_context(tmp_path)
    venv = tmp_path / "venv"
    subprocess.run([sys.executable, "-m", "venv", str(venv)], check=True)
    python = venv / "bin" / "python"
    start = time.monotonic()
    installed = subprocess.run(
        [str(python), "-m", "pip", "install", "-q", "--disable-pip-version-check", _pip_target()],
        cwd=context,
        capture_output=True,
        text=True,
        timeout=900,
    )
    assert installed.returncode == 0, installed.stderr[-3000:]
    print(f"fresh venv install of {_pip_target()}: {time.monotonic() - start:.0f} s")
    command = _compose()["services"]["migrate"]["command"]
    assert command[0] == "python3"
    with fresh_database(postgres_admin_url) as url:
        assert make_url(url).drivername == compose_driver  # postgresql+psycopg
        env = {k: v for k, v in os.environ.items() if not k.startswith("MONOLOC_")}
        env.update(MONOLOC_DATABASE_URL=url, MONOLOC_DATA_DIR=str(tmp_path / "data"))
        migrated = subprocess.run(
            [str(python), *command[1:]], cwd=tmp_path, env=env, capture_output=True, text=True
        )
        assert migrated.returncode == 0, migrated.stderr[-3000:]
        engine = create_engine(url)
        try:
            assert {"maps", "entries", "api_keys"} <= set(inspect(engine).get_table_names())
        finally:
            engine.dispose()


def test_the_volumes_the_compose_file_writes_to_are_the_image_users():
    lines = _dockerfile_lines()
    user = next(line.split()[1] for line in lines if line.startswith("USER "))
    owned: set[str] = set()
    for line in lines:
        for found in re.finditer(rf"chown {user}:{user} ((?:/[\w/-]+ ?)+)", line):
            owned.update(found.group(1).split())
    volumes = {
        v for line in lines if line.startswith("VOLUME") for v in re.findall(r'"(/[^"]+)"', line)
    }
    env = _replica_environment()
    replica = _compose()["services"]["monoloc-1"]
    mounts = {volume.split(":")[1] for volume in replica["volumes"]}
    for name in ("MONOLOC_DATA_DIR", "MONOLOC_UPLOADS_DIR", "TMPDIR"):
        path = env[name]
        mount = next((m for m in mounts if path == m or path.startswith(m + "/")), None)
        assert mount is not None, f"{name}={path} is on no volume of the replica"
        assert mount in owned, f"{name}={path}: {mount} is not {user}'s in the image"
        assert mount in volumes, f"{mount} is not a VOLUME of the image"
    # one TMPDIR: start.sh's comment names the compose file's
    assert env["TMPDIR"] in (DOCKER / "start.sh").read_text()


def _compose_command() -> list[str]:
    """Docker's compose plugin, else Debian's docker-compose (``make test`` installs it when
    neither is there): both validate a compose file offline, no daemon or image needed."""
    docker = shutil.which("docker")
    if docker is not None:
        probe = subprocess.run([docker, "compose", "version"], capture_output=True, text=True)
        if probe.returncode == 0:
            return [docker, "compose"]
    legacy = shutil.which("docker-compose")
    assert legacy is not None, "neither 'docker compose' nor docker-compose: run make test"
    return [legacy]


def _compose_config(path: Path) -> subprocess.CompletedProcess:
    return subprocess.run(
        [*_compose_command(), "-f", str(path), "config", "--quiet"],
        capture_output=True,
        text=True,
        env={**os.environ, "MONOLOC_BOOTSTRAP_ADMIN_KEY": ADMIN_KEY},
        timeout=120,
    )


def test_docker_compose_accepts_the_compose_file_and_refuses_a_broken_one(tmp_path):
    done = _compose_config(DOCKER / "compose.yaml")
    assert done.returncode == 0, done.stderr
    # the same file with an option compose does not know: the check is a real one
    broken = tmp_path / "compose.yaml"
    broken.write_text(
        (DOCKER / "compose.yaml").read_text() + "\nservices:\n  monoloc-1:\n    bogus_key: 1\n"
    )
    refused = _compose_config(broken)
    assert refused.returncode != 0 and "bogus_key" in (refused.stderr + refused.stdout)


def _start_sh(env: dict[str, str], log: Path) -> subprocess.Popen:
    with open(log, "ab") as out:
        return subprocess.Popen(["sh", str(DOCKER / "start.sh")], env=env, stdout=out, stderr=out)


def _wait_http(url: str, what: Path, timeout_s: float = 180.0) -> None:
    deadline = time.monotonic() + timeout_s
    while True:
        try:
            if httpx.get(url, timeout=10).status_code == 200:
                return
        except httpx.TransportError:
            pass
        assert time.monotonic() < deadline, what.read_text()[-3000:] if what.exists() else url
        time.sleep(0.1)


def _stop(processes: list[subprocess.Popen]) -> None:
    for process in processes:
        if process.poll() is None:
            process.terminate()
    for process in processes:
        try:
            process.wait(40)
        except subprocess.TimeoutExpired:
            process.kill()
            process.wait()


@contextmanager
def _deployment(postgres_admin_url: str, tmp: Path) -> Iterator[str]:
    """start.sh's steps as compose.yaml runs them: the migration once, then two replicas
    with the compose file's environment (hosts and paths on loopback / under ``tmp``),
    behind docker/nginx.conf. Yields nginx's URL."""
    from pg_cluster import fresh_database

    nginx = find_nginx()
    if nginx is None:
        pytest.fail("nginx is not installed (make test installs Debian's nginx-light)")
    with fresh_database(postgres_admin_url) as url:
        base = {k: v for k, v in os.environ.items() if not k.startswith("MONOLOC_")}
        compose_env = _replica_environment()
        compose_env.update(
            MONOLOC_DATABASE_URL=url,
            MONOLOC_UPLOADS_DIR=str(tmp / "shared" / "uploads"),
            TMPDIR=str(tmp / "shared" / "tmp"),  # start.sh makes it
            MONOLOC_BOOTSTRAP_ADMIN_KEY=ADMIN_KEY,
            MONOLOC_HOST="127.0.0.1",
            MONOLOC_WORKER_THREADS="1",
        )
        (tmp / "shared").mkdir()
        migrate = {**base, **compose_env, "MONOLOC_DATA_DIR": str(tmp / "migrate")}
        command = _compose()["services"]["migrate"]["command"]
        subprocess.run([sys.executable, *command[1:]], env=migrate, check=True, cwd=tmp)
        ports = [free_port(), free_port()]
        processes: list[subprocess.Popen] = []
        conf = None
        try:
            for n, port in enumerate(ports):
                env = {**base, **generous_env(), **compose_env}
                env.update(
                    MONOLOC_DATA_DIR=str(tmp / f"r{n}" / "data"),
                    MONOLOC_PORT=str(port),
                    MONOLOC_PYTHON=sys.executable,
                )
                processes.append(_start_sh(env, tmp / f"r{n}.log"))
            for n, port in enumerate(ports):
                _wait_http(f"http://127.0.0.1:{port}/readyz", tmp / f"r{n}.log")
            for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi"):
                (tmp / kind).mkdir()
            front_port = free_port()
            conf = loopback_nginx_conf(tmp, ports, front_port)
            subprocess.run([nginx, "-p", str(tmp), "-c", str(conf)], check=True)
            front = f"http://127.0.0.1:{front_port}"
            _wait_http(f"{front}/readyz", tmp / "error.log", 60)
            yield front
        finally:
            if conf is not None:
                subprocess.run([nginx, "-p", str(tmp), "-c", str(conf), "-s", "quit"], check=False)
            _stop(processes)


def _first_event(url: str, headers: dict, wait_s: float) -> tuple[str, float]:
    """The first ``data:`` line of an event stream and the seconds it took."""
    start = time.monotonic()
    timeout = httpx.Timeout(wait_s, connect=10)
    with httpx.stream("GET", url, headers=headers, timeout=timeout) as answer:
        assert answer.status_code == 200, answer.read()
        for line in answer.iter_lines():
            if line.startswith("data: "):
                return line, time.monotonic() - start
    raise AssertionError("the event stream ended without an event")


def test_start_sh_replicas_behind_nginx_localize_and_stream_live_events(
    postgres_admin_url, street, tmp_path
):
    with _deployment(postgres_admin_url, tmp_path) as front:
        admin = {"X-API-Key": ADMIN_KEY}
        keys = {"admin": ADMIN_KEY}
        for name, scope in (("localize", "localize"), ("write", "map:write")):
            made = httpx.post(
                f"{front}/v1/keys", json={"name": name, "scopes": [scope]}, headers=admin
            )
            assert made.status_code == 201, made.text
            keys[name] = made.json()["key"]
        map_id = create_map(front, keys, "street", street)
        job = wait_job(front, upload_run(front, keys, map_id, street, "00"), admin)
        assert job["state"] == "done", job
        assert (tmp_path / "shared" / "tmp").is_dir()  # start.sh made the compose TMPDIR
        frame = (street / "sequences" / "01" / "image_0" / "000007.png").read_bytes()
        answer = httpx.post(
            f"{front}/v1/maps/{map_id}/localize",
            files={"image": ("f.png", frame, "image/png")},
            headers={"X-API-Key": keys["localize"]},
            timeout=60,
        )
        assert answer.status_code == 200, answer.text
        assert answer.json()["hypotheses"], answer.json()
        # The live page's events: the first snapshot comes at once (nginx buffering an
        # open-ended answer would hold it until the server ends the stream, 30 s later).
        events = f"{front}/v1/maps/{map_id}/vehicles/events"
        line, took_s = _first_event(events, {"X-API-Key": keys["localize"]}, wait_s=10)
        assert '"vehicles": []' in line and took_s < 5, (line, took_s)
