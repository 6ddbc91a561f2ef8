"""File helpers shared by every program: atomic writes and token files.

``atomic_write`` is the one way the project replaces a file: write a temporary file beside the
target, flush and fsync it, then ``os.replace`` it into place, so a reader (or a crash half-way)
sees either the old content or the new, never a torn file.
"""

from __future__ import annotations

import os
from pathlib import Path


def atomic_write(path: str | Path, data: bytes | str, mode: int = 0o644) -> Path:
    """Replace ``path`` with ``data`` (str is written as UTF-8), durably; the file gets ``mode``."""
    path = Path(path)
    raw = data.encode("utf-8") if isinstance(data, str) else data
    tmp = path.with_name(f".{path.name}.tmp")
    fd = os.open(tmp, os.O_WRONLY | os.O_CREAT | os.O_TRUNC, mode)
    try:
        with os.fdopen(fd, "wb") as fh:
            fh.write(raw)
            fh.flush()
            os.fsync(fh.fileno())
        os.chmod(tmp, mode)  # os.open's mode is masked by the umask
        os.replace(tmp, path)
    except BaseException:
        tmp.unlink(missing_ok=True)
        raise
    return path


def write_private(path: str | Path, text: str) -> Path:
    """Write ``text`` to ``path`` with mode 0600, atomically (tokens, credentials)."""
    return atomic_write(path, text, mode=0o600)


def read_token(path: str | Path) -> str:
    """A bearer token from a file (first line, stripped); a clear error when missing or empty."""
    p = Path(path)
    try:
        tok = p.read_text(encoding="utf-8").strip()
    except OSError as exc:
        raise ValueError(f"cannot read token file {p}: {exc.strerror}") from None
    if not tok:
        raise ValueError(f"token file {p} is empty")
    return tok
