"""Independent checks of `twinswarm run` MCAP logs with the PyPI `mcap` reader (CRCs validated),
`mcap-protobuf-support`, `foxglove-schemas-protobuf` and `protobuf`.

Run by scripts/test.sh with TWINSWARM_BIN pointing at the debug binary.
"""

import json
import os
import signal
import subprocess
import sys
import time
from collections import defaultdict
from pathlib import Path

import pytest
from google.protobuf import descriptor_pb2
from mcap.reader import make_reader

from conftest import log_bodies, log_messages, loopback_endpoint, shared_data_or_skip

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
BIN = Path(os.environ.get("TWINSWARM_BIN", HERE / "../../target/debug/twinswarm")).resolve()
PROTO_DIR = REPO / "crates" / "bridge" / "proto"
DT_S = 0.05  # the lab's control step


def twinswarm(*args, cwd=None, timeout=300):
    return subprocess.run([str(BIN), *map(str, args)], capture_output=True, text=True, cwd=cwd, timeout=timeout)


def run_args(*args):
    """`twinswarm run` with `args`, its Zenoh node on a free loopback port (not the default 7447)."""
    return ["run", *map(str, args), "--listen", loopback_endpoint()]


@pytest.fixture(scope="session", autouse=True)
def binary():
    if not BIN.exists():
        pytest.fail(f"twinswarm binary not found at {BIN} (set TWINSWARM_BIN or run cargo build -p twinswarm)")


@pytest.fixture(scope="module")
def run_log(tmp_path_factory):
    path = tmp_path_factory.mktemp("run") / "lab.mcap"
    r = twinswarm(*run_args("--duration", "10", "--log", path))
    assert r.returncode == 0, r.stderr
    assert str(path) in r.stdout, r.stdout
    return path


def read_all(path):
    """Summary, metadata, attachments and every message, CRCs checked."""
    with open(path, "rb") as f:
        reader = make_reader(f, validate_crcs=True)
        summary = reader.get_summary()
        metadata = {m.name: dict(m.metadata) for m in reader.iter_metadata()}
        attachments = {a.name: a for a in reader.iter_attachments()}
        messages = [(schema, channel, msg) for schema, channel, msg in reader.iter_messages(log_time_order=False)]
    return summary, metadata, attachments, messages


def test_paparazzi_traffic_is_logged_as_text_and_decoded(run_log):
    """The default scene's virtual copters (ac_id 201, 202) publish telemetry: each message is
    on /pprz/<sender>/<NAME> as Ivy text and on .../decoded as fields, one for one."""
    texts, decoded = defaultdict(list), defaultdict(list)
    for channel, _msg, body in log_messages(run_log):
        if channel.topic.startswith("/pprz/"):
            if channel.topic.endswith("/decoded"):
                decoded[channel.topic[: -len("/decoded")]].append(body)
            else:
                texts[channel.topic].append(body)
    senders = {t.split("/")[2] for t in texts}
    assert {"201", "202"} <= senders, sorted(texts)
    for name in ("ATTITUDE", "SONAR_ARRAY", "FINKEN_ACTUATORS_SET_POINT", "ROTORCRAFT_FP"):
        assert f"/pprz/201/{name}" in texts, sorted(texts)
    for topic, items in texts.items():
        _, _, sender, name = topic.split("/")
        assert len(decoded[topic]) == len(items), topic
        for t, d in zip(items, decoded[topic]):
            assert t["direction"] == "out" and t["text"].split(" ")[:2] == [sender, name]
            assert d["sender"] == sender and d["name"] == name and d["fields"], d
    # 10 s at the plan's periods, capped at the 20 Hz control rate.
    assert len(texts["/pprz/201/ATTITUDE"]) == 200
    assert len(texts["/pprz/201/ROTORCRAFT_FP"]) == 40
    fp = decoded["/pprz/201/ROTORCRAFT_FP"][-1]["fields"]
    assert 0.7 / 0.0039063 < fp["up"] < 0.9 / 0.0039063, "the copter holds 0.8 m"


def test_channels_counts_times_and_records(run_log):
    summary, metadata, attachments, messages = read_all(run_log)
    assert summary is not None, "a finished log has a summary section"
    for channel in summary.channels.values():
        assert channel.schema_id != 0 and channel.schema_id in summary.schemas, f"{channel.topic} has no schema"
        assert channel.message_encoding == "protobuf"
        assert summary.schemas[channel.schema_id].encoding == "protobuf"
    topics = {c.topic for c in summary.channels.values()}
    assert {"/copters/state", "/copters/sensors", "/copters/command", "/copters/control", "/events", "/log", "/tf",
            "/scene/arena", "/scene/copters"} <= topics

    meta = metadata["twinswarm"]
    copters = json.loads(meta["copters"])
    steps = round(10 / DT_S)
    counts = defaultdict(int)
    last = {}
    for _schema, channel, msg in messages:
        counts[channel.topic] += 1
        assert msg.log_time >= last.get(channel.topic, 0), f"{channel.topic}: log_time not monotonic"
        last[channel.topic] = msg.log_time
        if channel.topic == "/bus" or channel.topic.startswith("/pprz/"):
            # Bus traffic: publish_time is the wall-clock send or receive time.
            assert msg.publish_time >= int(metadata["twinswarm"]["epoch_unix_ns"]) - 10**9
        else:
            assert msg.publish_time == msg.log_time
    assert counts["/copters/state"] == steps * len(copters)
    assert counts["/tf"] == steps * len(copters)
    assert counts["/scene/copters"] == steps // 4, "every 0.2 s"
    assert counts["/scene/arena"] == 1
    assert counts["/events"] >= len(copters), "every copter takes off"
    for cid, channel in summary.channels.items():
        assert summary.statistics.channel_message_counts.get(cid, 0) == counts[channel.topic]
    epoch = int(meta["epoch_unix_ns"])
    assert last["/copters/state"] == epoch + steps * 50_000_000
    assert meta["world"] == "lab" and meta["seed"] == "2016"
    assert "--duration 10" in meta["command_line"]
    scene = attachments["scene.toml"]
    assert scene.media_type == "application/toml"
    assert b'name = "lab"' in scene.data


def test_every_channel_decodes_with_the_files_own_schemas(run_log):
    """mcap-protobuf-support decodes every message of every channel with the descriptor sets in
    the file, and no message carries a field its schema does not declare (log_messages checks)."""
    seen = defaultdict(int)
    for channel, _msg, body in log_messages(run_log):
        seen[channel.topic] += 1
        if channel.topic == "/copters/state":
            assert len(body["pos_m"]) == 3 and len(body["quat_xyzw"]) == 4 and body["copter"].startswith("finken")
        if channel.topic == "/copters/sensors":
            assert len(body["sonar_m"]) == 4 and len(body["sonar_crosstalk"]) == 4 and 0 < body["battery_v"] < 20
    for topic in ("/copters/state", "/copters/sensors", "/copters/command", "/copters/control", "/events", "/log",
                  "/tf", "/scene/arena", "/scene/copters", "/bus"):
        assert seen[topic] > 0, (topic, dict(seen))
    assert any(t.startswith("/pprz/") and t.endswith("/decoded") for t in seen), sorted(seen)


def test_the_checked_in_descriptor_set_is_made_from_the_checked_in_proto(tmp_path, run_log):
    """twinswarm.fds (what every log embeds) is what scripts/gen-proto.sh makes from
    twinswarm.proto today, and it is the schema of the project's channels in a log."""
    out = tmp_path / "regenerated.fds"
    r = subprocess.run([str(REPO / "scripts" / "gen-proto.sh"), str(out)], capture_output=True, text=True,
                       env={**os.environ, "PYTHON": sys.executable})
    assert r.returncode == 0, r.stderr
    checked_in = (PROTO_DIR / "twinswarm.fds").read_bytes()
    assert out.read_bytes() == checked_in, "run scripts/gen-proto.sh after editing twinswarm.proto"
    with open(run_log, "rb") as f:
        summary = make_reader(f).get_summary()
    own = [s for s in summary.schemas.values() if s.name.startswith("twinswarm.")]
    assert own and all(s.data == checked_in for s in own), [s.name for s in own]


def test_foxglove_channels_decode_with_foxglove_schemas_protobuf(run_log):
    """The foxglove.* channels decode with PyPI foxglove-schemas-protobuf's own classes (not the
    file's descriptors), with nothing left over; and their fields are the properties of
    Foxglove's JSON schemas of the same messages (../shared/data/foxglove)."""
    from foxglove_schemas_protobuf.FrameTransform_pb2 import FrameTransform
    from foxglove_schemas_protobuf.Log_pb2 import Log
    from foxglove_schemas_protobuf.SceneUpdate_pb2 import SceneUpdate
    from google.protobuf.unknown_fields import UnknownFieldSet

    classes = {"foxglove.SceneUpdate": SceneUpdate, "foxglove.FrameTransform": FrameTransform, "foxglove.Log": Log}
    checked = defaultdict(int)
    with open(run_log, "rb") as f:
        for schema, _channel, msg in make_reader(f, validate_crcs=True).iter_messages():
            if schema.name in classes:
                m = classes[schema.name].FromString(msg.data)
                assert len(UnknownFieldSet(m)) == 0, schema.name
                assert m.SerializeToString() == msg.data, f"{schema.name}: re-encodes to the same bytes"
                checked[schema.name] += 1
                # The file's descriptor defines the same fields as the package's.
                fds = descriptor_pb2.FileDescriptorSet.FromString(schema.data)
                name = schema.name.removeprefix("foxglove.")
                fields = {(fd.name, fd.number) for fi in fds.file for mt in fi.message_type if mt.name == name
                          for fd in mt.field}
                assert fields == {(fd.name, fd.number) for fd in classes[schema.name].DESCRIPTOR.fields}
    assert set(checked) == set(classes), checked
    foxglove_dir = shared_data_or_skip("foxglove")
    for name, cls in classes.items():
        ref = json.loads((foxglove_dir / (name.removeprefix("foxglove.") + ".json")).read_text())
        assert set(ref["properties"]) == {fd.name for fd in cls.DESCRIPTOR.fields}, name


def test_json_logs_of_before_still_read(tmp_path):
    """A JSON log of the last JSON version (tests/fixtures): log info, plot and the readers."""
    old = REPO / "tests" / "fixtures" / "log-json-v1.mcap"
    r = twinswarm("log", "info", old)
    assert r.returncode == 0, r.stderr
    assert "json" in r.stdout and "/copters/state" in r.stdout
    out = tmp_path / "heat.png"
    r = twinswarm("plot", old, "--heatmap", out, "--attitude", tmp_path / "a.png", "--sonar", tmp_path / "s.png")
    assert r.returncode == 0, r.stderr
    assert out.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert len(log_bodies(old, "/copters/state")) == 80
    fixed = tmp_path / "recovered.mcap"
    r = twinswarm("log", "recover", old, fixed)
    assert r.returncode == 0, r.stderr
    assert [b["pos_m"] for b in log_bodies(fixed, "/copters/state")] == \
        [b["pos_m"] for b in log_bodies(old, "/copters/state")], "recover keeps the JSON messages"
    r = twinswarm("replay", old, "--no-bus", "--foxglove", "127.0.0.1:0", "--speed", "50")
    assert r.returncode == 0, r.stderr


def test_log_rate_thins_the_steps_but_keeps_every_event(tmp_path):
    full, thin = tmp_path / "full.mcap", tmp_path / "thin.mcap"
    for path, extra in ((full, []), (thin, ["--log-rate", "5"])):
        r = twinswarm(*run_args("--duration", "4", "--no-bus", "--log", path, *extra))
        assert r.returncode == 0, r.stderr
    full_ticks = sorted({b["tick"] for b in log_bodies(full, "/copters/state")})
    thin_ticks = sorted({b["tick"] for b in log_bodies(thin, "/copters/state")})
    assert full_ticks == list(range(1, 81))
    assert thin_ticks == list(range(4, 81, 4)), "5 Hz of a 20 Hz control loop: every 4th step"
    events = [(b["tick"], b["kind"]) for b in log_bodies(full, "/events")]
    assert events and [(b["tick"], b["kind"]) for b in log_bodies(thin, "/events")] == events, "every event"
    # Attachments, schemas and the copters' 5 Hz scene stay: the file shrinks by less than 4x.
    assert thin.stat().st_size < 0.75 * full.stat().st_size
    r = twinswarm(*run_args("--duration", "1", "--no-bus", "--no-log", "--log-rate", "0"))
    assert r.returncode == 2 and "--log-rate" in r.stderr, r.stderr


def test_a_lighter_zstd_level_writes_the_same_messages(tmp_path):
    light, default = tmp_path / "light.mcap", tmp_path / "default.mcap"
    for path, extra in ((default, []), (light, ["--log-zstd-level", "2"])):
        r = twinswarm(*run_args("--duration", "4", "--no-bus", "--log", path, *extra))
        assert r.returncode == 0, r.stderr
    states = log_bodies(default, "/copters/state")
    assert len(states) == 80 * len({b["copter"] for b in states}), "every step of every copter"
    assert log_bodies(light, "/copters/state") == states
    assert log_bodies(light, "/events") == log_bodies(default, "/events")
    for bad in ("0", "20", "x"):
        r = twinswarm(*run_args("--duration", "1", "--no-bus", "--log-zstd-level", bad))
        assert r.returncode == 2 and "--log-zstd-level" in r.stderr, r.stderr


PER_COPTER = ("/copters/state", "/copters/sensors", "/copters/command", "/copters/control", "/tf")


def per_copter_samples(path):
    """{(tick, copter name): {topic: body without its time fields}} of a log's per-copter channels."""
    samples = defaultdict(dict)
    epoch = int(metadata_of(path)["epoch_unix_ns"])
    for channel, message, body in log_messages(path, list(PER_COPTER)):
        if channel.topic == "/tf":
            name, tick = body["child_frame_id"], None
            body = {k: v for k, v in body.items() if k != "timestamp"}
        else:
            name, tick = body["copter"], body["tick"]
            body = {k: v for k, v in body.items() if k not in ("tick", "t_s")}
        key = ((message.log_time - epoch) // 50_000_000, name)
        samples[key][channel.topic] = body
        if tick is not None:
            samples[key]["tick"] = tick
    return samples


def test_unchanged_copters_are_held_and_nothing_is_lost(twinswarm_bin, tmp_path):
    """A wreck at rest is written once a second, not every step; holding each copter's last
    message until its next gives back the log that writes every copter every step."""
    scene = tmp_path / "dense.toml"
    scene.write_text(twinswarm("scene", "dense", "--n", "64", "--spacing", "1.0").stdout)
    full, held = tmp_path / "full.mcap", tmp_path / "held.mcap"
    for path, extra in ((full, ["--log-unchanged", "0"]), (held, [])):
        r = twinswarm(*run_args(scene, "--duration", "8", "--no-bus", "--json", "--log", path, *extra))
        assert r.returncode == 0, r.stderr
    crashed = [c for c in json.loads(r.stdout)["copters"] if c["crashed"]]
    assert crashed, "wrecks to hold"
    a, b = per_copter_samples(full), per_copter_samples(held)
    assert all(len(v) == len(PER_COPTER) + 1 for v in a.values()), "five messages per copter and step"
    assert all(len(v) == len(PER_COPTER) + 1 for v in b.values()), "a copter is written whole or not at all"
    assert set(b) < set(a), "the held log writes fewer samples, none the full one lacks"
    assert all(b[k] == a[k] for k in b), "what is written is what the full log has"
    meta = metadata_of(held)
    every = int(meta["unchanged_every_ticks"])
    assert every == 20 and int(metadata_of(full)["unchanged_every_ticks"]) == 1
    names = {name for _t, name in a}
    times = sorted({t for t, _name in a})
    assert len(times) == 160
    last = {}
    for t in times:
        for name in names:
            if (t, name) in b:
                last[name] = b[(t, name)]
            else:
                assert a[(t, name)]["tick"] % every != 0, f"{name}: every copter on whole seconds"
                assert name in last, f"{name}: held before it was written"
            got = dict(last[name], tick=a[(t, name)]["tick"])
            assert got == a[(t, name)], f"{name} at {t}: the held message is not the full log's"
    held_out = len(a) - len(b)
    assert held_out > 0
    for bad in ("--log-unchanged=-1", "--log-unchanged=inf", "--log-unchanged=x"):
        r = twinswarm(*run_args(scene, "--duration", "1", "--no-bus", "--no-log", bad))
        assert r.returncode == 2 and "--log-unchanged" in r.stderr, r.stderr


def metadata_of(path):
    with open(path, "rb") as f:
        return {m.name: dict(m.metadata) for m in make_reader(f, validate_crcs=True).iter_metadata()}["twinswarm"]


def state_ticks(path):
    return {b["tick"] for b in log_bodies(path, "/copters/state")}


def test_kill_9_loses_at_most_about_a_second(tmp_path):
    broken, fixed = tmp_path / "killed.mcap", tmp_path / "fixed.mcap"
    proc = subprocess.Popen([str(BIN), *run_args("--duration", "600", "--realtime", "--log", broken)],
                            stdout=subprocess.DEVNULL, stderr=subprocess.PIPE)
    started = time.monotonic()
    try:
        time.sleep(3.0)
        assert proc.poll() is None, proc.stderr.read().decode()
        proc.send_signal(signal.SIGKILL)
        killed_after_s = time.monotonic() - started
    finally:
        proc.kill()
        proc.wait(timeout=10)
    r = twinswarm("log", "recover", broken, fixed)
    assert r.returncode == 0, r.stderr
    assert "recovered" in r.stdout
    ticks = state_ticks(fixed)
    recovered_s = max(ticks) * DT_S if ticks else 0.0
    assert recovered_s >= 1.0, f"only {recovered_s:.2f} s recovered"
    assert recovered_s <= killed_after_s + 0.1
    assert killed_after_s - recovered_s <= 1.5, f"killed after {killed_after_s:.2f} s, recovered {recovered_s:.2f} s"
    assert ticks == set(range(1, max(ticks) + 1)), "no step missing"


@pytest.mark.parametrize("sig", [signal.SIGINT, signal.SIGTERM])
def test_sigint_and_sigterm_finish_the_file_cleanly(tmp_path, sig):
    path = tmp_path / "stopped.mcap"
    proc = subprocess.Popen([str(BIN), *run_args("--duration", "600", "--realtime", "--log", path)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        time.sleep(1.5)
        proc.send_signal(sig)
        out, err = proc.communicate(timeout=20)
    finally:
        proc.kill()
    assert proc.returncode == 0, err
    assert "interrupted" in out and str(path) in out, out
    summary, _, _, messages = read_all(path)
    assert summary is not None and summary.statistics.message_count == len(messages)
    kinds = [b["kind"] for b in log_bodies(path, "/events")]
    assert kinds[-1] == "interrupted", kinds


def test_default_log_path_and_no_log(tmp_path):
    r = twinswarm(*run_args("--duration", "1"), cwd=tmp_path)
    assert r.returncode == 0, r.stderr
    logs = list((tmp_path / "runs").glob("lab-*.mcap"))
    assert len(logs) == 1, logs
    assert logs[0].name[4:20].endswith("Z") and "T" in logs[0].name, logs[0].name
    assert f"runs/{logs[0].name}" in r.stdout, r.stdout
    r = twinswarm(*run_args("--duration", "1", "--no-log"), cwd=tmp_path)
    assert r.returncode == 0 and "off" in r.stdout
    assert len(list((tmp_path / "runs").glob("*.mcap"))) == 1


def test_info_and_plots(run_log, tmp_path):
    r = twinswarm("log", "info", run_log)
    assert r.returncode == 0, r.stderr
    for text in ["/copters/state", "twinswarm.CopterState", "400", "finken1", "scene.toml", "duration 10.00 s"]:
        assert text in r.stdout, (text, r.stdout)
    outs = [tmp_path / n for n in ("heat.png", "att.png", "sonar.png")]
    r = twinswarm("plot", run_log, "--heatmap", outs[0], "--attitude", outs[1], "--sonar", outs[2])
    assert r.returncode == 0, r.stderr
    for p in outs:
        assert p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"


def test_bad_files_exit_2_with_a_clear_error(run_log, tmp_path):
    data = run_log.read_bytes()
    cases = {"empty.mcap": b"", "text.mcap": b"not a log\n" * 10, "cut.mcap": data[: len(data) // 2]}
    for name, content in cases.items():
        p = tmp_path / name
        p.write_bytes(content)
        for args in (["log", "info", p], ["plot", p, "--heatmap", tmp_path / "x.png"]):
            r = twinswarm(*args)
            assert r.returncode == 2, (args, r.returncode, r.stderr)
            assert r.stderr.startswith("error:") and "panicked" not in r.stderr, r.stderr
    r = twinswarm("log", "recover", tmp_path / "empty.mcap", tmp_path / "out.mcap")
    assert r.returncode == 2 and "empty" in r.stderr, r.stderr
