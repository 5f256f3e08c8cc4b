"""Independent checks of `twinswarm run` MCAP logs with the PyPI `mcap` reader and `jsonschema`.

Run by scripts/test.sh with TWINSWARM_BIN pointing at the debug binary.
"""

import json
import os
import signal
import subprocess
import time
from collections import defaultdict
from pathlib import Path

import jsonschema
import pytest
from mcap.reader import make_reader
from referencing import Registry, Resource
from referencing.jsonschema import DRAFT202012

from conftest import loopback_endpoint, shared_data_or_skip

HERE = Path(__file__).resolve().parent
REPO = HERE.parents[1]
BIN = Path(os.environ.get("TWINSWARM_BIN", HERE / "../../target/debug/twinswarm")).resolve()
SCHEMA_DIR = REPO / "crates" / "bridge" / "schemas"
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
    _summary, _metadata, _attachments, messages = read_all(run_log)
    texts, decoded = defaultdict(list), defaultdict(list)
    for _schema, channel, msg in messages:
        if channel.topic.startswith("/pprz/"):
            body = json.loads(msg.data)
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


def validator(schema_json, registry=None):
    cls = jsonschema.validators.validator_for(schema_json, default=jsonschema.Draft202012Validator)
    cls.check_schema(schema_json)
    return cls(schema_json, registry=registry) if registry is not None else cls(schema_json)


def test_channels_counts_times_and_records(run_log):
    summary, metadata, attachments, messages = read_all(run_log)
    assert summary is not None, "a finished log has a summary section"
    for channel in summary.channels.values():
        assert channel.schema_id != 0 and channel.schema_id in summary.schemas, f"{channel.topic} has no schema"
        assert channel.message_encoding == "json"
        assert summary.schemas[channel.schema_id].encoding == "jsonschema"
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


def test_payloads_validate_against_file_and_checked_in_schemas(run_log):
    summary, _, _, messages = read_all(run_log)
    checked_in = {p.stem: json.loads(p.read_text()) for p in SCHEMA_DIR.glob("*.json")}
    in_file = {}
    ours = {}
    seen = defaultdict(int)
    for schema, channel, msg in messages:
        if schema.id not in in_file:
            data = json.loads(schema.data)
            assert data.get("title") == schema.name, f"schema {schema.name}: title {data.get('title')}"
            in_file[schema.id] = validator(data)
            assert schema.name in checked_in, f"{schema.name} is not checked in under {SCHEMA_DIR}"
            ours[schema.id] = validator(checked_in[schema.name])
        payload = json.loads(msg.data)
        in_file[schema.id].validate(payload)
        ours[schema.id].validate(payload)
        seen[schema.name] += 1
    assert len(seen) >= 8, seen


def foxglove_registry(foxglove_dir):
    resources = []
    for p in sorted(foxglove_dir.glob("*.json")):
        contents = json.loads(p.read_text())
        resource = Resource.from_contents(contents, default_specification=DRAFT202012)
        resources += [(p.name, resource), (contents["title"], resource)]
    return Registry().with_resources(resources)


def test_foxglove_channels_validate_against_the_reference_schemas(run_log):
    foxglove_dir = shared_data_or_skip("foxglove")
    registry = foxglove_registry(foxglove_dir)
    validators = {}
    _, _, _, messages = read_all(run_log)
    checked = defaultdict(int)
    for schema, channel, msg in messages:
        if not schema.name.startswith("foxglove."):
            continue
        if schema.name not in validators:
            ref = foxglove_dir / (schema.name.removeprefix("foxglove.") + ".json")
            assert ref.exists(), f"no reference schema for {schema.name}"
            validators[schema.name] = validator(json.loads(ref.read_text()), registry)
        validators[schema.name].validate(json.loads(msg.data))
        checked[schema.name] += 1
    assert set(checked) == {"foxglove.FrameTransform", "foxglove.SceneUpdate", "foxglove.Log"}, checked


def state_ticks(path):
    ticks = set()
    with open(path, "rb") as f:
        for _schema, _channel, msg in make_reader(f, validate_crcs=True).iter_messages(topics=["/copters/state"]):
            ticks.add(json.loads(msg.data)["tick"])
    return ticks


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
    kinds = [json.loads(m.data)["kind"] for _s, c, m in messages if c.topic == "/events"]
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
