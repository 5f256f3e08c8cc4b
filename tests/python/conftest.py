"""Shared fixtures: the twinswarm binary and free loopback ports."""
import os
import pathlib
import socket

import pytest

ROOT = pathlib.Path(__file__).resolve().parents[2]


@pytest.fixture(scope="session")
def twinswarm_bin() -> pathlib.Path:
    path = pathlib.Path(os.environ.get("TWINSWARM_BIN", ROOT / "target" / "debug" / "twinswarm"))
    if not path.exists():
        pytest.fail(f"twinswarm binary not found at {path}: build it with `cargo build -p twinswarm`")
    return path


@pytest.fixture
def free_port() -> int:
    with socket.socket(socket.AF_INET, socket.SOCK_STREAM) as s:
        s.bind(("127.0.0.1", 0))
        return s.getsockname()[1]
