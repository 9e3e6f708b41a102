"""A throwaway pg_auto_failover formation for the shard suites: a monitor, a primary and
a secondary (``pg_autoctl create ... --run``) on 127.0.0.1, trust authentication, no
TLS, data under a temporary directory; as root (CI containers) every ``pg_autoctl`` runs
as the ``postgres`` system user (initdb refuses root). Debian: postgresql-NN-auto-failover
and pg-auto-failover-cli (``make system-deps``)."""

from __future__ import annotations

import json
import os
import pwd
import shutil
import subprocess
import tempfile
import time
from dataclasses import dataclass, field
from pathlib import Path

from pg_cluster import find_pg_bin


def find_pg_autoctl() -> str | None:
    return shutil.which("pg_autoctl") or (
        "/usr/bin/pg_autoctl" if Path("/usr/bin/pg_autoctl").exists() else None
    )


@dataclass
class AutoFailoverFormation:
    """Monitor on ``ports[0]``, nodes on ``ports[1]`` and ``ports[2]``, database ``dbname``."""

    root: Path
    ports: tuple[int, int, int]
    dbname: str = "monoloc"
    processes: list[subprocess.Popen] = field(default_factory=list)

    @property
    def monitor_uri(self) -> str:
        return f"postgres://autoctl_node@127.0.0.1:{self.ports[0]}/pg_auto_failover?sslmode=disable"

    @property
    def url(self) -> str:
        """A multi-host SQLAlchemy URL: libpq tries both nodes and keeps the one that
        accepts writes (``target_session_attrs=read-write``), so after a failover a new
        connection lands on the new primary."""
        hosts = "&".join(f"host=127.0.0.1:{p}" for p in self.ports[1:])
        return (
            f"postgresql+psycopg://postgres@/{self.dbname}?{hosts}&target_session_attrs=read-write"
        )

    def _env(self) -> dict[str, str]:
        bin_dir = find_pg_bin()
        assert bin_dir is not None
        return {
            "PATH": f"{bin_dir}:/usr/bin:/bin",
            "HOME": str(self.root),
            "XDG_CONFIG_HOME": str(self.root / "config"),
            "XDG_DATA_HOME": str(self.root / "share"),
            "XDG_RUNTIME_DIR": str(self.root / "run"),
            "PGHOST": str(self.root),  # the nodes' Unix sockets (-k, and where to look)
            "PG_REGRESS_SOCK_DIR": str(self.root),
            "LC_ALL": "C.UTF-8",
        }

    def _cmd(self, *args: str) -> list[str]:
        env = [f"{k}={v}" for k, v in self._env().items()]
        cmd = ["env", "-i", *env, find_pg_autoctl() or "pg_autoctl", *args]
        return ["runuser", "-u", "postgres", "--", *cmd] if os.geteuid() == 0 else cmd

    def autoctl(self, *args: str, timeout_s: float = 120) -> str:
        done = subprocess.run(
            self._cmd(*args), capture_output=True, text=True, timeout=timeout_s, check=False
        )
        if done.returncode != 0:
            raise RuntimeError(f"pg_autoctl {' '.join(args)}: {done.stderr[-2000:]}")
        return done.stdout

    def _run(self, name: str, *args: str) -> None:
        log = open(self.root / f"{name}.log", "ab")  # noqa: SIM115 - the process keeps it
        self.processes.append(subprocess.Popen(self._cmd(*args), stdout=log, stderr=log))

    def states(self) -> dict[int, tuple[str, str]]:
        """port -> (reported state, assigned state) of each node, as the monitor says."""
        out = self.autoctl("show", "state", "--pgdata", str(self.root / "monitor"), "--json")
        nodes = json.loads(out) if out.strip() else []
        return {
            int(n["nodeport"]): (n.get("current_group_state"), n.get("assigned_group_state"))
            for n in nodes
            if "nodeport" in n
        }

    def wait_states(self, wanted: dict[int, str], timeout_s: float = 240) -> None:
        """Until every node of ``wanted`` reports its state (and is assigned it); a
        CHECKPOINT on the primary now and then so that a standby's base backup does not
        wait for the next timed one."""
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                states = self.states()
            except RuntimeError:
                states = {}
            if all(states.get(p) == (s, s) for p, s in wanted.items()):
                return
            if time.monotonic() > deadline:
                raise AssertionError(f"formation states {states}, wanted {wanted}: {self.logs()}")
            self._checkpoint()
            time.sleep(1.0)

    def _checkpoint(self) -> None:
        bin_dir = find_pg_bin()
        for port in self.ports[1:]:
            cmd = [str(bin_dir / "psql"), "-h", "127.0.0.1", "-p", str(port), "-U", "postgres"]
            cmd += ["-d", "postgres", "-Atc", "SELECT pg_is_in_recovery()"]
            probe = subprocess.run(cmd, capture_output=True, text=True, timeout=10, check=False)
            if probe.stdout.strip() == "f":
                cmd[-1] = "CHECKPOINT"
                subprocess.run(cmd, capture_output=True, timeout=30, check=False)

    def start(self) -> None:
        self.root.mkdir(parents=True, exist_ok=True)
        for sub in ("config", "share", "run"):
            (self.root / sub).mkdir(exist_ok=True)
        # pg_autoctl keeps each node's state under XDG_{CONFIG,DATA}_HOME/pg_autoctl/<its
        # PGDATA path>; two of its processes making those directories at once (a node
        # starting while `show` polls the monitor) race, and the loser exits "File exists":
        # make them all first
        for sub in ("config", "share"):
            for pgdata in ["monitor", *(f"node{i}" for i in range(1, len(self.ports)))]:
                state = self.root / sub / "pg_autoctl" / str(self.root / pgdata).lstrip("/")
                state.mkdir(parents=True, exist_ok=True)
        if os.geteuid() == 0:
            user = pwd.getpwnam("postgres")
            for path in [self.root, *self.root.rglob("*")]:
                os.chown(path, user.pw_uid, user.pw_gid)
        common = ["--hostname", "127.0.0.1", "--listen", "127.0.0.1", "--auth", "trust"]
        common += ["--no-ssl"]
        self._run(
            "monitor",
            "create",
            "monitor",
            "--pgdata",
            str(self.root / "monitor"),
            "--pgport",
            str(self.ports[0]),
            *common,
            "--run",
        )
        for i, port in enumerate(self.ports[1:], start=1):
            self._wait_monitor()
            self._run(
                f"node{i}",
                "create",
                "postgres",
                "--pgdata",
                str(self.root / f"node{i}"),
                "--pgport",
                str(port),
                "--name",
                f"node{i}",
                "--dbname",
                self.dbname,
                "--monitor",
                self.monitor_uri,
                *common,
                "--run",
            )
            if i == 1:
                self.wait_states({port: "single"})
        self.wait_states({self.ports[1]: "primary", self.ports[2]: "secondary"})

    def _wait_monitor(self, timeout_s: float = 120) -> None:
        deadline = time.monotonic() + timeout_s
        while True:
            try:
                self.autoctl("show", "uri", "--pgdata", str(self.root / "monitor"))
                return
            except RuntimeError:
                if time.monotonic() > deadline:
                    raise AssertionError(f"the monitor did not start: {self.logs()}") from None
                time.sleep(0.5)

    def primary_port(self) -> int:
        primary = [p for p, (s, _) in self.states().items() if s in ("primary", "wait_primary")]
        assert len(primary) == 1, self.states()
        return primary[0]

    def failover(self) -> None:
        """``pg_autoctl perform failover``: the secondary becomes the primary (returns
        once the monitor reports it)."""
        self.autoctl("perform", "failover", "--pgdata", str(self.root / "monitor"))

    def logs(self) -> str:
        return "\n".join(
            f"--- {log.name}\n{log.read_text(errors='replace')[-1500:]}"
            for log in sorted(self.root.glob("*.log"))
        )

    def stop(self) -> None:
        for name in ("node2", "node1", "monitor"):
            pgdata = self.root / name
            if pgdata.exists():
                subprocess.run(
                    self._cmd("stop", "--pgdata", str(pgdata), "--fast"),
                    capture_output=True,
                    timeout=60,
                    check=False,
                )
        for process in self.processes:
            try:
                process.wait(30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait(10)
        shutil.rmtree(self.root, ignore_errors=True)


def start_formation(ports: tuple[int, int, int]) -> AutoFailoverFormation | None:
    """A started formation, or None when pg_autoctl or PostgreSQL is not installed."""
    if find_pg_autoctl() is None or find_pg_bin() is None:
        return None
    root = Path(tempfile.mkdtemp(prefix="mlaf", dir="/tmp"))
    os.chmod(root, 0o755)
    formation = AutoFailoverFormation(root, ports)
    try:
        formation.start()
    except BaseException:
        formation.stop()
        raise
    return formation
