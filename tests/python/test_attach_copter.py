"""A real Zenoh client (PyPI eclipse-zenoh) commands a copter of a running `twinswarm run
--realtime` 0.5 m up and sees it in the state stream; then SIGTERM stops the simulator cleanly."""
import json
import signal
import subprocess
import sys
import time

import zenoh

from conftest import ROOT, log_bodies, zenoh_client_config


def test_python_client_flies_a_copter_up(twinswarm_bin, free_port, tmp_path):
    endpoint = f"tcp/127.0.0.1:{free_port}"
    log = tmp_path / "attach.mcap"
    sim = subprocess.Popen(
        [str(twinswarm_bin), "run", "--realtime", "--duration", "120", "--log", str(log), "--listen", endpoint, "--json"],
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
        # A malformed command: rejected, counted, and logged with its source key.
        with zenoh.open(zenoh_client_config(endpoint)) as session:
            time.sleep(0.5)
            session.put("twinswarm/lab/copters/finken2/cmd", '{"throttle": "full"}')
            time.sleep(0.5)
    finally:
        sim.send_signal(signal.SIGTERM)
        out, err = sim.communicate(timeout=30)
    assert sim.returncode == 0, f"clean shutdown on SIGTERM, got {sim.returncode}: {err}"
    summary = json.loads(out)
    assert summary["bus"]["commands_accepted"] >= 1
    assert summary["bus"]["clients_seen"] >= 1
    assert summary["control_steps"] < 120 * 20, "stopped early by SIGTERM"
    assert summary["bus"]["commands_rejected"] >= 1

    # The log holds the bus inputs with their keys, and the rejection as an event.
    bus, events = log_bodies(log, "/bus"), log_bodies(log, "/events")
    keys = {m["key"] for m in bus}
    assert "twinswarm/lab/copters/finken1/cmd" in keys, keys
    assert "twinswarm/lab/copters/finken2/cmd" in keys, keys
    assert any(e["kind"] == "input_rejected" for e in events), events
