"""TLS for `posecast serve --certfile C --keyfile K` (wss://) and its `--origins` list.

The context is built, and every file read, before the server listens: a missing, unreadable,
malformed, encrypted or mismatched certificate or key is one ``TLSConfigError`` line for
the user, not a traceback at the first client's handshake. TLS 1.2 is the oldest version
accepted (1.0 and 1.1 are deprecated by RFC 8996).
"""

from __future__ import annotations

import asyncio
import gc
import re
import ssl
from collections.abc import Sequence
from pathlib import Path
from typing import cast

from websockets.typing import Origin

# scheme://host[:port], as browsers send the Origin header (no path, no trailing slash)
_ORIGIN = re.compile(r"(?P<scheme>https?)://(?P<host>\[[0-9A-Fa-f:.]+\]|[A-Za-z0-9.-]+)"
                     r"(?::(?P<port>\d{1,5}))?")


class TLSConfigError(ValueError):
    """The certificate or key cannot serve TLS; ``str()`` is one line naming the file."""


def server_tls_context(certfile: Path, keyfile: Path) -> ssl.SSLContext:
    """A server context for ``certfile`` (PEM: the certificate, then any intermediates)
    and its unencrypted private key ``keyfile``; TLSConfigError says what is wrong."""
    cert_text = _read_pem("--certfile", certfile)
    key_text = _read_pem("--keyfile", keyfile)
    if "-----BEGIN CERTIFICATE-----" not in cert_text:
        raise TLSConfigError(f"--certfile {str(certfile)!r} holds no PEM certificate "
                             "(-----BEGIN CERTIFICATE-----)")
    if "ENCRYPTED" in key_text:
        # the server starts unattended: nobody could type a passphrase
        raise TLSConfigError(f"--keyfile {str(keyfile)!r} is encrypted with a passphrase; "
                             "give an unencrypted key readable only by the server's user")
    if not re.search(r"-----BEGIN [A-Z ]*PRIVATE KEY-----", key_text):
        raise TLSConfigError(f"--keyfile {str(keyfile)!r} holds no PEM private key "
                             "(-----BEGIN PRIVATE KEY-----)")
    context = ssl.SSLContext(ssl.PROTOCOL_TLS_SERVER)
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    try:
        context.load_cert_chain(certfile, keyfile, password=_no_passphrase)
    except ssl.SSLError as err:
        if "KEY_VALUES_MISMATCH" in str(err) or "key values mismatch" in str(err):
            raise TLSConfigError(f"--keyfile {str(keyfile)!r} is not the key of the "
                                 f"certificate in --certfile {str(certfile)!r}") from None
        raise TLSConfigError(f"cannot use --certfile {str(certfile)!r} with --keyfile "
                             f"{str(keyfile)!r}: {err.reason or err}") from None
    except OSError as err:
        raise TLSConfigError(f"cannot load --certfile {str(certfile)!r} and --keyfile "
                             f"{str(keyfile)!r}: {err.strerror or err}") from None
    return context


def _read_pem(option: str, path: Path) -> str:
    try:
        return path.read_text(encoding="ascii", errors="replace")
    except OSError as err:
        raise TLSConfigError(f"cannot read {option} {str(path)!r}: {err.strerror or err}"
                             ) from None


def _no_passphrase() -> bytes:
    # called only for an encrypted key that got past the check above: never prompt
    raise TLSConfigError("the key is encrypted with a passphrase")


def check_origin(text: str) -> str:
    """One browser origin for ``--origins``: scheme://host[:port], as the Origin header
    carries it (http or https, no path); ValueError in words otherwise."""
    found = _ORIGIN.fullmatch(text)
    if found is None:
        raise ValueError(f"must be origins such as https://example.org or "
                         f"http://localhost:8000 (scheme://host[:port], no path), got {text!r}")
    port = found.group("port")
    if port is not None and not 1 <= int(port) <= 65535:
        raise ValueError(f"has a port outside 1..65535: {text!r}")
    return text.lower()  # browsers send the scheme and host in lower case


def allowed_origins(origins: Sequence[str] | None) -> list[Origin | None] | None:
    """websockets' ``origins=`` for an allow-list: None (no list) lets every request in;
    with a list, a request without an Origin header is still let in: browsers always
    send one, so it comes from a program such as our own clients."""
    if not origins:
        return None
    return [*map(Origin, origins), None]


def tcp_under_tls(transport: asyncio.BaseTransport) -> asyncio.WriteTransport | None:
    """The TCP transport under a TLS transport, whose write buffer neither asyncio nor
    uvloop lets one size (None where it cannot be found). Called once per connection."""
    layer = getattr(transport, "_ssl_protocol", None)  # asyncio's TLS layer
    if layer is None:  # uvloop's is compiled: its fields are reachable as gc referents
        layer = next((r for r in gc.get_referents(transport)
                      if type(r).__name__ == "SSLProtocol"), None)
    if layer is None:
        return None
    below = getattr(layer, "_transport", None)
    if below is None:
        below = next((r for r in gc.get_referents(layer)
                      if type(r).__name__ == "TCPTransport"), None)
    if below is None or below is transport or not hasattr(below, "set_write_buffer_limits"):
        return None
    return cast(asyncio.WriteTransport, below)
