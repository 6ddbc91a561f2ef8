"""The server's guards: bearer tokens that can be rotated while it runs, failed sign-ins logged and
rate-limited per client address, an audit log of operator actions, and the refusal to listen
beyond loopback without TLS.

Tokens live in files (mode 0600). The server re-reads a token file when its modification time
changes, so `training-server rotate-token` takes effect at the next request, without a restart;
the old token stops working at once.
"""

from __future__ import annotations

import hmac
import ipaddress
import json
import logging
import os
import secrets
import threading
import time
from collections import deque
from pathlib import Path
from typing import Any

from shared.core.files import read_token, write_private

log = logging.getLogger("mures.server.security")

ROLES = ("operator", "agent")
MAX_FAILURES = 10  # failed sign-ins from one address within WINDOW_S before it is refused
WINDOW_S = 60.0


def new_token() -> str:
    return secrets.token_urlsafe(32)


class TokenFile:
    """A bearer token read from a file, re-read when the file changes (rotation)."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._mtime = -1.0
        self._token = ""
        self._lock = threading.Lock()

    def get(self) -> str:
        with self._lock:
            mtime = self.path.stat().st_mtime_ns
            if mtime != self._mtime:
                self._token = read_token(self.path)
                self._mtime = mtime
            return self._token

    def matches(self, presented: bytes) -> bool:
        """Constant-time comparison with the current token."""
        return hmac.compare_digest(presented, self.get().encode())


def rotate(path: Path) -> None:
    """Write a fresh token to ``path`` (0600): the old one is refused from the next request on."""
    write_private(path, new_token() + "\n")


class SignInGuard:
    """Counts failed sign-ins per client address: more than MAX_FAILURES within WINDOW_S and the
    address is refused (429) until the window has passed. Every failure is logged."""

    def __init__(self, max_failures: int = MAX_FAILURES, window_s: float = WINDOW_S) -> None:
        self.max_failures, self.window_s = max_failures, window_s
        self._fails: dict[str, deque[float]] = {}
        self._lock = threading.Lock()

    def _recent(self, client: str, now: float) -> deque[float]:
        q = self._fails.setdefault(client, deque())
        while q and now - q[0] > self.window_s:
            q.popleft()
        return q

    def blocked_for(self, client: str) -> float:
        """Seconds this address must wait, 0 when it may try."""
        now = time.monotonic()
        with self._lock:
            q = self._recent(client, now)
            if len(q) < self.max_failures:
                return 0.0
            return max(0.0, self.window_s - (now - q[0]))

    def failed(self, client: str, why: str, path: str) -> None:
        now = time.monotonic()
        with self._lock:
            q = self._recent(client, now)
            q.append(now)
            n = len(q)
        log.warning("failed sign-in from %s on %s: %s (%d in the last %.0f s)", client, path, why, n, self.window_s)


class AuditLog:
    """One JSON line per operator action (who, what, when, the answer) in ``audit.jsonl``."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self._lock = threading.Lock()

    def write(self, **entry: Any) -> None:
        line = json.dumps({"ts": round(time.time(), 3), **entry}, separators=(",", ":"))
        with self._lock:
            fd = os.open(self.path, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o600)
            with os.fdopen(fd, "a", encoding="utf-8") as fh:
                fh.write(line + "\n")

    def read(self) -> list[dict[str, Any]]:
        if not self.path.exists():
            return []
        return [json.loads(x) for x in self.path.read_text(encoding="utf-8").splitlines() if x.strip()]


def is_loopback(host: str) -> bool:
    if host == "localhost":
        return True
    try:
        return ipaddress.ip_address(host.strip("[]")).is_loopback
    except ValueError:
        return False  # a host name: assume it is reachable from the network


def endpoint_host(endpoint: str) -> tuple[str, str]:
    """(protocol, host) of a Zenoh endpoint such as tcp/127.0.0.1:7447 or tls/[::1]:7447."""
    proto, _, rest = endpoint.partition("/")
    host = rest.rsplit(":", 1)[0] if ":" in rest else rest
    return proto, host
