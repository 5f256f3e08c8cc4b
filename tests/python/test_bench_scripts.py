"""Smoke passes of the scaling scripts whose figures docs/performance.md quotes (§11): each runs
end to end on a small swarm and a short flight, on the test build, and writes what the docs
read. The figures themselves come from release builds and long runs (docs/performance.md)."""
import json
import os
import pathlib
import subprocess
import sys

ROOT = pathlib.Path(__file__).resolve().parents[2]


def scene(twinswarm_bin, tmp_path, n=60):
    path = tmp_path / "dense.toml"
    path.write_text(subprocess.run([str(twinswarm_bin), "scene", "dense", "--n", str(n), "--seed", "2"],
                                   check=True, capture_output=True, text=True).stdout)
    return path


def test_scaling_py_writes_the_table_the_json_and_the_plot(twinswarm_bin, tmp_path):
    md, js, svg = tmp_path / "s.md", tmp_path / "s.json", tmp_path / "s.svg"
    got = subprocess.run(
        [sys.executable, str(ROOT / "scripts" / "scaling.py"), "--bin", str(twinswarm_bin), "--sizes", "60",
         "--threads", "1,2", "--shards", "1,2", "--duration", "1", "--md", str(md), "--json", str(js),
         "--svg", str(svg)],
        capture_output=True, text=True, timeout=300)
    assert got.returncode == 0, got.stderr[-3000:]
    rows = json.loads(js.read_text())["rows"]
    assert [(r["kind"], r["shards"]) for r in rows] == [("run", 1), ("run", 1), ("cluster", 1), ("cluster", 2)]
    assert [r["threads"] for r in rows[:2]] == [1, 2]
    assert all(r["differ"] == 0 for r in rows), rows
    for r in rows:
        # The CPU account is there for every run: work over one thread's, and how busy the cores were.
        assert r["cpu_per_sim_s"] and r["cpu_per_sim_s"] > 0, r
        assert r["cores_busy"] and 0 < r["cores_busy"] < 4, r
    assert rows[0]["work_over_1_thread"] == 1.0
    table = md.read_text()
    assert "CPU per simulated s over 1 thread's" in table and "| 60 | 2 shards ×" in table, table
    assert svg.read_text().startswith("<svg") and "Amdahl" in svg.read_text()


def test_shards_vs_threads_sh_prints_the_ratios_and_the_cpu_account(twinswarm_bin, tmp_path):
    got = subprocess.run(["bash", str(ROOT / "scripts" / "shards-vs-threads.sh"), str(scene(twinswarm_bin, tmp_path)),
                          "1", "1"], env={**os.environ, "TWINSWARM": str(twinswarm_bin)},
                         capture_output=True, text=True, timeout=300)
    assert got.returncode == 0, got.stderr[-3000:]
    assert "medians of the ratios: 2 threads" in got.stdout, got.stdout
    assert "nan" not in got.stdout, got.stdout


def test_ab_py_compares_two_builds_and_fails_when_their_bits_differ(twinswarm_bin, tmp_path):
    path = scene(twinswarm_bin, tmp_path)
    ab = [sys.executable, str(ROOT / "scripts" / "ab.py"), "cluster", "1", "1", str(path)]
    got = subprocess.run(ab + [str(twinswarm_bin), str(twinswarm_bin)], capture_output=True, text=True, timeout=300)
    assert got.returncode == 0, got.stderr[-3000:]
    assert "medians:" in got.stdout and "in_shm" in got.stdout, got.stdout
    # A "build" whose copters end elsewhere: the same binary on another seed of the same scene.
    other = tmp_path / "other"
    other.write_text(f'#!/bin/sh\nexec "{twinswarm_bin}" "$@" --seed 9\n')
    other.chmod(0o755)
    got = subprocess.run([sys.executable, str(ROOT / "scripts" / "ab.py"), "run", "1", "1", str(path),
                          str(twinswarm_bin), str(other)], capture_output=True, text=True, timeout=300)
    assert got.returncode == 1 and "digests differ" in got.stdout, (got.stdout, got.stderr[-2000:])


def test_scaling_py_fails_when_a_thread_count_changes_the_bits(twinswarm_bin, tmp_path):
    # A "build" whose two-thread runs fly another seed: its digests must be caught.
    wrapper = tmp_path / "twinswarm"
    wrapper.write_text(f'#!/bin/sh\ncase "$*" in *"--threads 2"*) exec "{twinswarm_bin}" "$@" --seed 9;; esac\n'
                       f'exec "{twinswarm_bin}" "$@"\n')
    wrapper.chmod(0o755)
    got = subprocess.run([sys.executable, str(ROOT / "scripts" / "scaling.py"), "--bin", str(wrapper), "--sizes", "60",
                          "--threads", "1,2", "--shards", "", "--duration", "1"],
                         capture_output=True, text=True, timeout=300)
    assert got.returncode != 0 and "other digests than one thread's" in got.stderr, (got.stdout, got.stderr[-2000:])
    two = next(line for line in got.stdout.splitlines() if line.startswith("| 60 | 2 threads |"))
    assert int(two.rstrip(" |").rsplit("|", 1)[1]) > 0, two


def test_scaling_py_writes_its_table_between_the_docs_markers_and_refuses_a_file_without_them(
        twinswarm_bin, tmp_path):
    doc = tmp_path / "perf.md"
    doc.write_text("# before\n<!-- scaling.py: begin -->\nold table\n<!-- scaling.py: end -->\nafter\n")
    run = [sys.executable, str(ROOT / "scripts" / "scaling.py"), "--bin", str(twinswarm_bin), "--sizes", "40",
           "--threads", "1", "--shards", "", "--duration", "0.5", "--docs", str(doc)]
    got = subprocess.run(run, capture_output=True, text=True, timeout=300)
    assert got.returncode == 0, got.stderr[-3000:]
    text = doc.read_text()
    assert text.startswith("# before\n<!-- scaling.py: begin -->\n`python3 scripts/scaling.py"), text
    assert "old table" not in text and "| 40 | 1 thread |" in text and text.endswith("<!-- scaling.py: end -->\nafter\n")
    assert (tmp_path / "scaling.svg").read_text().startswith("<svg")
    # Without the markers it stops before measuring anything, and leaves the file alone.
    doc.write_text("no markers here\n")
    got = subprocess.run(run, capture_output=True, text=True, timeout=300)
    assert got.returncode != 0 and "must hold one" in got.stderr and "copters" not in got.stderr, got.stderr
    assert doc.read_text() == "no markers here\n"
