"""The one way the gateway reads a file it is told to read (config, model, EDS).

:func:`read_regular` opens without blocking (a FIFO does not hang the open), refuses
anything that is not a regular file (a device such as ``/dev/zero``, a FIFO, a socket,
also behind a symlink) at once, and refuses a file above the caller's size limit before
reading it, so a wrong path can cost neither unbounded memory nor unbounded time.
"""

from __future__ import annotations

import os
import stat
from pathlib import Path

from gateway.errors import ConfigError

MAX_YAML_BYTES = 4 << 20  # a config or model file: a few kB in practice
MAX_EDS_BYTES = 4 << 20  # an EDS: ~60 kB for the shipped ones

_KINDS = {
    stat.S_IFCHR: "a character device",
    stat.S_IFBLK: "a block device",
    stat.S_IFIFO: "a FIFO",
    stat.S_IFSOCK: "a socket",
    stat.S_IFDIR: "a directory",
}


def read_regular(path: str | Path, max_bytes: int, what: str = "file") -> bytes:
    """The bytes of the regular file ``path``; ConfigError naming it otherwise."""
    try:
        fd = os.open(path, os.O_RDONLY | os.O_NONBLOCK | os.O_CLOEXEC)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    try:
        st = os.fstat(fd)
        if not stat.S_ISREG(st.st_mode):
            kind = _KINDS.get(stat.S_IFMT(st.st_mode), "not a regular file")
            raise ConfigError(f"{path}: is {kind}, not a regular {what}")
        if st.st_size > max_bytes:
            raise ConfigError(
                f"{path}: {st.st_size} bytes, more than a {what} may have ({max_bytes})"
            )
        chunks, size = [], 0
        while size <= max_bytes:  # the file may grow while it is read: still bounded
            chunk = os.read(fd, max_bytes + 1 - size)
            if not chunk:
                break
            chunks.append(chunk)
            size += len(chunk)
        if size > max_bytes:
            raise ConfigError(f"{path}: more than a {what} may have ({max_bytes} bytes)")
        return b"".join(chunks)
    except OSError as exc:
        raise ConfigError(f"{path}: cannot read: {exc.strerror or exc}") from exc
    finally:
        os.close(fd)
