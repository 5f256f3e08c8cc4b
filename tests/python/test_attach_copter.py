"""A real Zenoh client (PyPI eclipse-zenoh) commands a copter of a running `twinswarm run
--realtime` 0.5 m up and sees it in the state stream; then SIGTERM stops the simulator cleanly."""
import json
import signal
import subprocess
import sys
import time

from conftest import ROOT


def test_python_client_flies_a_copter_up(twinswarm_bin, free_port):
    endpoint = f"tcp/127.0.0.1:{free_port}"
    sim = subprocess.Popen(
        [str(twinswarm_bin), "run", "--realtime", "--duration", "120", "--no-log", "--listen", endpoint, "--json"],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    try:
        time.sleep(1.0)  # let it open its session and take off
        client = subprocess.run(
            [sys.executable, str(ROOT / "examples" / "python" / "attach_copter.py"), "twinswarm/lab", "finken1", endpoint],
            capture_output=True,
            text=True,
            timeout=60,
        )
        assert client.returncode == 0, client.stderr
        assert "climbed from" in client.stdout, client.stdout
        print(client.stdout.strip())
    finally:
        sim.send_signal(signal.SIGTERM)
        out, err = sim.communicate(timeout=30)
    assert sim.returncode == 0, f"clean shutdown on SIGTERM, got {sim.returncode}: {err}"
    summary = json.loads(out)
    assert summary["bus"]["commands_accepted"] >= 1
    assert summary["bus"]["clients_seen"] >= 1
    assert summary["control_steps"] < 120 * 20, "stopped early by SIGTERM"
