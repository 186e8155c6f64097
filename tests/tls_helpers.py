"""Self-signed certificates for loopback TLS tests and benches (the openssl command)."""

from __future__ import annotations

import subprocess
from pathlib import Path


def self_signed(directory: Path | str, name: str) -> tuple[Path, Path]:
    """A self-signed EC P-256 certificate for 127.0.0.1 (CN and subjectAltName), valid one
    day: ``(directory/name.pem, directory/name.key)``."""
    cert, key = Path(directory) / f"{name}.pem", Path(directory) / f"{name}.key"
    subprocess.run(
        [
            "openssl",
            "req",
            "-x509",
            "-newkey",
            "ec",
            "-pkeyopt",
            "ec_paramgen_curve:P-256",
            "-nodes",
            "-days",
            "1",
            "-subj",
            "/CN=127.0.0.1",
            "-addext",
            "subjectAltName=IP:127.0.0.1",
            "-keyout",
            str(key),
            "-out",
            str(cert),
        ],
        check=True,
        capture_output=True,
        timeout=60,
    )
    return cert, key
