"""What tests/python/test_nps.py and test_nps_firmware.py share: scripts/nps_swarm.py loaded as a
module, a flight through it with TWINSWARM_BIN, and the uplink through Paparazzi's `link`."""

import importlib.util
import os
import re

from conftest import ROOT
from pprz_ground import paparazzi_or_skip

SPEC = importlib.util.spec_from_file_location("nps_swarm", ROOT / "scripts" / "nps_swarm.py")
nps_swarm = importlib.util.module_from_spec(SPEC)
SPEC.loader.exec_module(nps_swarm)


def twinswarm_bin():
    return os.environ.get("TWINSWARM_BIN", str(ROOT / "target" / "debug" / "twinswarm"))


def fly(tmp_path, *args):
    paparazzi_or_skip()
    return nps_swarm.main(["--twinswarm", twinswarm_bin(), "--out", str(tmp_path), *map(str, args)])


SONAR_FIELDS = ["real_front", "real_right", "real_back", "real_left", "virt_front", "virt_right", "virt_back",
                "virt_left", "fused_front", "fused_right", "fused_back", "fused_left", "ir", "virt_age", "wa_roll",
                "wa_pitch", "ll_roll", "ll_pitch", "uplinks"]
# A virtual-only wall across the arena, its face 1 m ahead of where the copter starts (the
# arena's centre, heading +x), 0.4 m thick.
VIRTUAL_WALL = "pos_m = [1.2, 0.0]; size_m = [0.4, 3.0, 2.5]; virtual_only = true"


def uplink_runs(tmp_path, g, merged, first_ac, *args, runs=("a", "b")):
    """Flies the same run with the uplink through `link` (g) once per name in `runs`."""
    return [nps_swarm.main(list(map(str, [
        "--twinswarm", twinswarm_bin(), "--out", tmp_path / k, "--first-ac", first_ac, "--udp-out", g.link_port,
        "--udp-in", g.uplink_port, f"--run-arg=--ivy={g.bus}", f"--run-arg=--messages={merged}", *args])))
        for k in runs]


def assert_uplink_in_the_lockstep(r, ac):
    """The world counted the aircraft's uplink, and its NPS gave its autopilot what was named."""
    up = r["uplinks"][ac]
    assert up["uplink"] == "counted", r
    said = r["nps_said"][ac]
    assert "uplink in the lockstep" in said, said
    named, given = (int(v) for v in re.search(r"(\d+) named, (\d+) given", said).groups())
    # The uplink after the last step is named in no state; the last state may name one the
    # autopilot had no datalink event left to take.
    assert up["counted"] - 1 <= named <= up["counted"] and named - 1 <= given <= named, (said, up)
    return named
