"""What the HTTP layer costs the server per request, by uvicorn's HTTP implementation and
event loop (issue 14: under overload a replica answers many requests it does not compute).

Starts `monoloc serve` once per configuration (h11 + asyncio, uvicorn's pure-Python
fallback, as the baseline; httptools + uvloop, what the server extra installs) on an
empty data directory and sends, over one keep-alive connection each:

- ``GET /healthz`` (the smallest answer), and
- ``POST /v1/maps/1/localize`` with a camera-sized PNG (~100 kB) and an unknown key: the
  server refuses it before reading the body (401), as it sheds a request when the
  localize lane is full (503), so its cost is what an unread upload costs.

The figure is the server process's CPU time (user + system, from /proc) per request,
next to the baseline measured in the same run. Usage:
    python -m bench.http_overhead [--requests 2000] [--repeat 3]
"""

from __future__ import annotations

import argparse
import http.client
import json
import os
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parent.parent
RESULTS = Path(__file__).parent / "results"
WORK = ROOT / "out" / "bench_http_overhead"
CONFIGS = {
    "h11 + asyncio (baseline)": ("h11", "asyncio"),
    "httptools + uvloop": ("httptools", "uvloop"),
}


def free_port() -> int:
    with socket.socket() as sock:
        sock.bind(("127.0.0.1", 0))
        return sock.getsockname()[1]


def cpu_s(pid: int) -> float:
    """User + system CPU seconds of a process (its threads included), from /proc."""
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


def upload_body() -> tuple[bytes, str]:
    """A multipart body holding a 1241 x 376 PNG of noise (~100 kB after compression)."""
    import cv2

    rng = np.random.default_rng(0)
    image = cv2.GaussianBlur(rng.integers(0, 256, (376, 1241), dtype=np.uint8), (5, 5), 0)
    png = cv2.imencode(".png", image)[1].tobytes()
    boundary = "monolocbench"
    head = (
        f'--{boundary}\r\nContent-Disposition: form-data; name="image"; filename="f.png"\r\n'
        "Content-Type: image/png\r\n\r\n"
    ).encode()
    return head + png + f"\r\n--{boundary}--\r\n".encode(), boundary


def send(port: int, n: int, method: str, path: str, body: bytes | None, headers: dict) -> dict:
    """``n`` requests over keep-alive connections (a new one when the server closes);
    status counts and the number of connections used."""
    statuses: dict[int, int] = {}
    connections = 0
    conn = None
    for _ in range(n):
        if conn is None:
            conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
            connections += 1
        conn.request(method, path, body=body, headers=headers)
        response = conn.getresponse()
        response.read()
        statuses[response.status] = statuses.get(response.status, 0) + 1
        if response.getheader("connection", "").lower() == "close":
            conn.close()
            conn = None
    if conn is not None:
        conn.close()
    return {"statuses": statuses, "connections": connections}


def measure(parser_name: str, loop: str, n: int, body: bytes, boundary: str) -> dict:
    from monoloc.client.api import wait_until_ready

    data_dir = WORK / f"{parser_name}-{loop}"
    shutil.rmtree(data_dir, ignore_errors=True)
    port = free_port()
    cmd = [sys.executable, "-m", "monoloc.cli", "serve", "--port", str(port)]
    cmd += ["--data-dir", str(data_dir), "--log-level", "warning"]
    cmd += ["--http", parser_name, "--loop", loop]
    proc = subprocess.Popen(cmd, cwd=ROOT)
    try:
        wait_until_ready(f"http://127.0.0.1:{port}", 180.0, proc)
        send(port, 200, "GET", "/healthz", None, {})  # warm-up
        cases = {
            "GET /healthz": ("GET", "/healthz", None, {}),
            "POST localize, 100 kB, refused unread (401)": (
                "POST",
                "/v1/maps/1/localize",
                body,
                {
                    "X-API-Key": "mlk_" + "x" * 43,
                    "Content-Type": f"multipart/form-data; boundary={boundary}",
                },
            ),
        }
        out = {}
        for name, (method, path, payload, headers) in cases.items():
            before, t0 = cpu_s(proc.pid), time.perf_counter()
            sent = send(port, n, method, path, payload, headers)
            wall_s = time.perf_counter() - t0
            used_s = cpu_s(proc.pid) - before
            out[name] = {
                "server_cpu_us_per_request": 1e6 * used_s / n,
                "wall_us_per_request": 1e6 * wall_s / n,
                **sent,
            }
        return out
    finally:
        proc.terminate()
        proc.wait(60)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--requests", type=int, default=2000, help="per case and repeat")
    parser.add_argument("--repeat", type=int, default=3, help="alternating runs per config")
    args = parser.parse_args()
    body, boundary = upload_body()
    runs: dict[str, list[dict]] = {name: [] for name in CONFIGS}
    for _ in range(args.repeat):  # alternate, so a busier minute hits both
        for name, (parser_name, loop) in CONFIGS.items():
            runs[name].append(measure(parser_name, loop, args.requests, body, boundary))
    summary: dict[str, dict] = {}
    for name, measured in runs.items():
        summary[name] = {}
        for case in measured[0]:
            cpu = [m[case]["server_cpu_us_per_request"] for m in measured]
            summary[name][case] = {
                "server_cpu_us_per_request_median": float(np.median(cpu)),
                "server_cpu_us_per_request_runs": cpu,
                "statuses": measured[0][case]["statuses"],
                "connections": measured[0][case]["connections"],
            }
    base_name = next(iter(CONFIGS))
    print(f"server CPU per request (median of {args.repeat} runs, {args.requests} requests each)")
    for case in summary[base_name]:
        base = summary[base_name][case]["server_cpu_us_per_request_median"]
        print(f"  {case}")
        for name in CONFIGS:
            row = summary[name][case]
            ratio = row["server_cpu_us_per_request_median"] / base
            print(
                f"    {name:<26} {row['server_cpu_us_per_request_median']:8.0f} us  "
                f"({ratio:.2f}x baseline; statuses {row['statuses']}, "
                f"{row['connections']} connection(s))"
            )
    RESULTS.mkdir(exist_ok=True)
    path = RESULTS / "http_overhead.json"
    path.write_text(
        json.dumps({"requests": args.requests, "repeat": args.repeat, "results": summary}, indent=2)
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
