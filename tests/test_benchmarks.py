"""The benchmark scripts still run (a smoke test; speed itself is judged by reading their tables)."""

import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]


@pytest.mark.slow
def test_maps_benchmark_quick_writes_its_tables(tmp_path):
    out = tmp_path / "maps.md"
    done = subprocess.run(
        [sys.executable, "benchmarks/maps.py", "--quick", "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    text = out.read_text()
    for heading in ("## 1.", "## 2.", "## 3.", "targets"):
        assert heading in text
    assert "ILWRMap" in text and "sklearn GP" in text


@pytest.mark.slow
def test_shape_benchmark_writes_its_table(tmp_path):
    out = tmp_path / "shapes.md"
    maps = ["similarity", "authors' GP (sklearn)", "ILWRMap (default)"]
    done = subprocess.run([sys.executable, "benchmarks/shapes.py", "--shapes", "1", "--maps", *maps, "--out", str(out)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    text = out.read_text()
    first = text.split("## ")[0]  # the main table; calibration and stop-and-ask tables follow
    rows = [line.split(" | ") for line in first.splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert [r[0][2:] for r in rows] == maps and rows[1][6] == "1.00"  # the authors' GP is its own reference
    assert all(float(r[1]) > 0 for r in rows) and "42 ordered demonstration pairs" in text
    assert "one shape: nothing held out" in text  # a single shape leaves no held-out shape to calibrate on
    stop = [line for line in text.splitlines() if line.startswith("| ILWRMap (default) |")][-1].split(" | ")
    assert -1 <= float(stop[1]) <= 1 and len(stop) == 5  # Spearman, then three median / p90 cells


@pytest.mark.slow
def test_pusht_benchmarks_write_their_tables(tmp_path):
    runs = {
        "pusht_env.md": ["benchmarks/pusht_env.py", "--steps", "300", "--repeats", "1"],
        "pusht_expert.md": ["benchmarks/pusht_expert.py", "--n", "2", "--workers", "1", "--collect", "2"],
    }
    for name, cmd in runs.items():
        out = tmp_path / name
        done = subprocess.run(
            [sys.executable, *cmd, "--out", str(out)], cwd=ROOT, capture_output=True, text=True, timeout=600
        )
        assert done.returncode == 0, done.stderr[-3000:]
        assert "| " in out.read_text() and "steps" in out.read_text()
    assert "kpflow" in (tmp_path / "pusht_env.md").read_text()
    assert "object outside training region" in (tmp_path / "pusht_expert.md").read_text()


def test_metrics_benchmark_checks_itself_against_the_double_loop(tmp_path):
    out = tmp_path / "metrics.md"
    done = subprocess.run(
        [sys.executable, "benchmarks/metrics.py", "--sizes", "12", "--repeats", "1", "--out", str(out)],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert done.returncode == 0, done.stderr[-3000:]
    rows = [
        line.split("|")
        for line in out.read_text().splitlines()
        if line.startswith("| discrete") or line.startswith("| DTW")
    ]
    assert len(rows) == 2
    assert all(float(row[6]) < 1e-6 for row in rows)  # kpflow's value agrees with the cell-by-cell recursion


def test_store_read_benchmark_times_checked_against_unchecked_reads(tmp_path):
    from tests.helpers import walk_to_block_store

    walk_to_block_store(tmp_path / "demos.zarr")
    out = tmp_path / "store_read.md"
    cmd = [
        sys.executable,
        "benchmarks/store_read.py",
        "--stores",
        str(tmp_path / "demos.zarr"),
        "--repeats",
        "1",
        "--out",
        str(out),
    ]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert done.returncode == 0, done.stderr[-3000:]
    rows = [line.split("|") for line in out.read_text().splitlines() if line.startswith("| demos.zarr")]
    assert [row[5].strip() for row in rows] == ["every field whole", "every episode"]
    assert all(float(row[8]) > 0 for row in rows) and "Target (at most 10 % more time" in out.read_text()


@pytest.mark.slow
def test_learned_map_benchmark_writes_its_tables(tmp_path):
    from tests.helpers import keypoint_pair, train_learned_map, walk_to_block_store

    store = tmp_path / "demos.zarr"
    walk_to_block_store(store)

    def pairs(n, rng):
        src, tgt = keypoint_pair(2)
        return src.expand(n, -1, -1).numpy(), tgt.expand(n, -1, -1).numpy()

    ckpt = train_learned_map(tmp_path, pairs, n_keypoints=25, steps=2)
    out = tmp_path / "learned.md"
    cmd = [
        sys.executable,
        "benchmarks/learned_map.py",
        "--checkpoint",
        ckpt,
        "--store",
        str(store),
        "--quick",
        "--batch",
        "20",
        "--out",
        str(out),
    ]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=600)
    assert done.returncode == 0, done.stderr[-3000:]
    text = out.read_text()
    assert "| object-OOD resets (1024 px) |" in text and "| LearnedMap + 3 ILWR steps |" in text
    assert "det J > 0 at 100.00 %" in text  # by construction


@pytest.mark.slow
def test_serving_benchmark_writes_its_table(tmp_path):
    out = tmp_path / "serving.md"
    cmd = [
        sys.executable,
        "benchmarks/serving.py",
        "--requests",
        "5",
        "--steps",
        "2",
        "--clients",
        "1",
        "2",
        "--out",
        str(out),
    ]
    done = subprocess.run(cmd, cwd=ROOT, capture_output=True, text=True, timeout=300)
    assert done.returncode == 0, done.stderr[-3000:]
    rows = [line for line in out.read_text().splitlines() if line.startswith("| ") and "---" not in line][1:]
    assert len(rows) == 5 and rows[0].startswith("| in-process") and all(float(r.split(" | ")[2]) > 0 for r in rows)
    assert [r.split(" | ")[0] for r in rows[1:]] == ["| server, batching off"] * 2 + [
        "| server, batching on (8 rows, 5 ms)"
    ] * 2
