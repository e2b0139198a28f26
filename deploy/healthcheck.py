"""The container's HEALTHCHECK: exit 0 when `posecast serve` answers GET /healthz with 200,
else 1 with the reason on stderr (docker inspect shows it).

Standard library only: slim images have no curl. It asks the server on this machine, at
the port of the config file (``POSECAST_CONFIG``, default /etc/posecast/posecast.toml; 8765
without one) and over https when that file gives a certificate, since /healthz is served
on the websocket's own port. ``POSECAST_HEALTHZ_URL`` overrides all of it (a --port flag
given after the image's name, say).
"""

from __future__ import annotations

import os
import ssl
import sys
import tomllib
import urllib.error
import urllib.request
from pathlib import Path

DEFAULT_CONFIG = "/etc/posecast/posecast.toml"
DEFAULT_PORT = 8765  # posecast serve's default
TIMEOUT_S = 4.0  # under HEALTHCHECK --timeout, so the reason is ours, not a kill


def healthz_url(environ: dict[str, str]) -> str:
    if environ.get("POSECAST_HEALTHZ_URL"):
        return environ["POSECAST_HEALTHZ_URL"]
    config: dict[str, object] = {}
    path = Path(environ.get("POSECAST_CONFIG", DEFAULT_CONFIG))
    if path.is_file():
        config = tomllib.loads(path.read_text(encoding="utf-8"))
    port = config.get("port", DEFAULT_PORT)
    scheme = "https" if config.get("certfile") else "http"
    return f"{scheme}://127.0.0.1:{port}/healthz"


def main() -> int:
    try:
        url = healthz_url(dict(os.environ))
    except (OSError, ValueError) as err:  # tomllib's error is a ValueError
        print(f"healthcheck: cannot read the config: {err}", file=sys.stderr)
        return 1
    # the certificate names the public host, not 127.0.0.1, and this asks whether the
    # process serves, not who it is: no verification on this one loopback request
    context = ssl._create_unverified_context() if url.startswith("https:") else None
    try:
        with urllib.request.urlopen(url, timeout=TIMEOUT_S, context=context) as reply:
            status = reply.status
    except urllib.error.HTTPError as err:
        status = err.code
    except (OSError, ValueError) as err:
        print(f"healthcheck: {url}: {getattr(err, 'reason', err)}", file=sys.stderr)
        return 1
    if status != 200:
        print(f"healthcheck: {url} answered {status}", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    sys.exit(main())
