"""The one HTTP client of the project: the agent, fleet-sim, benchmarks and tests use it to talk to
the training server's REST API (docs/SPEC.md section 9). Standard library only (urllib), so a robot
computer needs nothing more.
"""

from __future__ import annotations

import json
import ssl
import urllib.error
import urllib.request
from typing import Any


class ApiError(RuntimeError):
    """The server answered with an error status; ``body`` is its JSON (or text) body."""

    def __init__(self, status: int, body: Any) -> None:
        super().__init__(f"HTTP {status}: {body}")
        self.status = status
        self.body = body


class ApiClient:
    """JSON in and out, a bearer token on every request. Network failures raise OSError
    (urllib's URLError included); error statuses raise ``ApiError``."""

    def __init__(
        self, base: str, token: str | None, timeout: float = 30.0, ca_file: str | None = None, actor: str | None = None
    ) -> None:
        """``ca_file``: the CA certificate (PEM) to verify an https server with, for a fleet's own
        CA or a self-signed server certificate; the system's CAs otherwise. ``actor``: who acts
        with the token, sent as X-Mures-Actor and kept in the server's audit log (a program acting
        for an operator says so: fleet-sim's simulated operator)."""
        self.actor = actor
        self.base = base.rstrip("/")
        self.token = token
        self.timeout = timeout
        self.context = ssl.create_default_context(cafile=ca_file) if ca_file else None

    def request(
        self,
        method: str,
        path: str,
        body: Any = None,
        headers: dict[str, str] | None = None,
        timeout: float | None = None,
    ) -> tuple[int, dict[str, str], bytes]:
        """(status, response headers with lower-case names, raw body). 304 Not Modified is returned,
        not raised."""
        data = None if body is None else json.dumps(body).encode()
        req = urllib.request.Request(self.base + path, data=data, method=method, headers=dict(headers or {}))
        if data is not None:
            req.add_header("Content-Type", "application/json")
        if self.token:
            req.add_header("Authorization", f"Bearer {self.token}")
        if self.actor:
            req.add_header("X-Mures-Actor", self.actor)
        try:
            with urllib.request.urlopen(req, timeout=timeout or self.timeout, context=self.context) as resp:
                return resp.status, {k.lower(): v for k, v in resp.headers.items()}, resp.read()
        except urllib.error.HTTPError as exc:
            if exc.code == 304:
                return 304, {k.lower(): v for k, v in exc.headers.items()}, b""
            raw = exc.read()
            try:
                payload = json.loads(raw)
            except ValueError:
                payload = raw.decode(errors="replace")
            raise ApiError(exc.code, payload) from None

    def call(self, method: str, path: str, body: Any = None, timeout: float | None = None) -> Any:
        _status, _headers, raw = self.request(method, path, body, timeout=timeout)
        return json.loads(raw) if raw else None

    def get(self, path: str) -> Any:
        return self.call("GET", path)

    def post(self, path: str, body: Any = None) -> Any:
        return self.call("POST", path, body if body is not None else {})
