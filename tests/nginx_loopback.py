"""An nginx config made runnable on loopback by an unprivileged test: its pid, logs and
temporary files under the test's directory (shared by the fleet and shard suites)."""

from __future__ import annotations

import os
import re
from pathlib import Path


def loopback_paths(tmp: Path, text: str, access_log: str) -> Path:
    """Write ``text`` (an nginx config whose access log is ``access_log /dev/stdout
    <access_log>;``) to ``tmp/nginx.conf`` with every path it writes under ``tmp``."""
    if f"access_log /dev/stdout {access_log};" not in text:
        raise AssertionError(f"the config has no `access_log /dev/stdout {access_log};`")
    text = re.sub(r"access_log /dev/stdout (\w+);", rf"access_log {tmp}/access.log \1;", text)
    temp = "\n".join(
        f"    {kind}_temp_path {tmp}/{kind};"
        for kind in ("client_body", "proxy", "fastcgi", "uwsgi", "scgi")
    )
    text = text.replace("http {\n", "http {\n" + temp + "\n", 1)
    text = f"pid {tmp}/nginx.pid;\nerror_log {tmp}/error.log;\n" + text
    if os.geteuid() == 0:  # workers would run as nobody, who cannot write under tmp
        text = "user root;\n" + text
    conf = tmp / "nginx.conf"
    conf.write_text(text)
    return conf
