"""TLS for the clients (`play`, `view`): whom a wss:// server must be vouched for by,
and a failed handshake in words for the user.

Without ``--cafile`` the system's default trust store decides (a certificate from a
public CA, e.g. Let's Encrypt, behind a proxy or in posecast); with it, that file's CA
certificates instead (a private CA, or a self-signed server certificate itself).
"""

from __future__ import annotations

import ssl
from pathlib import Path


class CAFileError(ValueError):
    """``--cafile`` cannot be used; ``str()`` is one line naming the file, ``why`` the
    reason alone."""

    def __init__(self, cafile: Path, why: str) -> None:
        super().__init__(f"--cafile {str(cafile)!r} {why}")
        self.why = why


def client_tls_context(cafile: Path | None = None) -> ssl.SSLContext:
    """The context for wss:// URLs: hostname checked, TLS 1.2 or later, trusting
    ``cafile`` (PEM CA certificates) if given, else the system's trust store."""
    if cafile is None:
        context = ssl.create_default_context()
    else:
        try:
            context = ssl.create_default_context(cafile=str(cafile))
        except ssl.SSLError as err:
            raise CAFileError(cafile, f"is not a PEM file of CA certificates "
                              f"({err.reason or err})") from None
        except OSError as err:
            raise CAFileError(cafile, f"is not readable ({err.strerror or err})") from None
    context.minimum_version = ssl.TLSVersion.TLSv1_2
    return context


def tls_failure(exc: BaseException, secure: bool) -> str | None:
    """Why a TLS handshake failed, in words, or None if ``exc`` is not about TLS;
    ``secure``: the URL was wss://."""
    if isinstance(exc, ssl.SSLCertVerificationError):
        why = exc.verify_message or exc.reason or str(exc)
        return (f"the server's certificate is not trusted: {why}; --cafile for a "
                f"private CA")
    if isinstance(exc, ssl.SSLError):
        # wss:// to a plain server: its HTTP reply is no TLS record
        return (f"TLS handshake failed ({exc.reason or exc}); if the server is not "
                f"serving TLS, use ws:// instead of wss://")
    if secure and isinstance(exc, ConnectionResetError):
        # a plain websocket server drops a TLS hello it cannot parse as HTTP
        return ("the server reset the connection during the TLS handshake; if it is not "
                "serving TLS, use ws:// instead of wss://")
    return None
