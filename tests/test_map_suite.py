"""The map suite's benchmarks: multi-frame scenes with independently turned frames, their keypoint pairs for the
learned map, distillation from another teacher, the suite recordings' round trip, and the suite script itself."""

import math
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import torch

from kpflow.maps import GPMap, ILWRMap
from kpflow.tasks.frames.pairs import FramesPairs
from kpflow.tasks.frames.turns import turned_configs, turned_families

ROOT = Path(__file__).resolve().parents[1]


def _angle(a, b) -> float:
    d = float(a.theta - b.theta)
    return abs(math.atan2(math.sin(d), math.cos(d)))


def test_turned_families_are_seeded_and_keep_each_demonstrators_style():
    a = turned_families(2, n_configs=3, n_demonstrators=2, seed=5)
    b = turned_families(2, n_configs=3, n_demonstrators=2, seed=5)
    assert len(a) == 2 and len(a[0].configs) == 3 and len(a[0].demos) == 3 and len(a[0].demos[0]) == 2
    for fa, fb in zip(a, b):
        for da, db in zip(fa.demos, fb.demos):
            assert all(torch.equal(x.positions, y.positions) for x, y in zip(da, db))
    family = a[0]
    start, goal = family.configs[1]
    for k in range(2):  # demonstrator k in configuration 1 is a fresh draw with k's own generator: the same path
        demo = family.demos[1][k]
        assert torch.allclose(demo.positions[0], start.position) and torch.allclose(demo.positions[-1], goal.position)
    assert not torch.allclose(family.demos[1][0].positions, family.demos[1][1].positions)  # demonstrators differ


def test_turned_configs_turn_each_frame_within_half_the_range_and_shift_within_bounds():
    g = torch.Generator().manual_seed(0)
    base = turned_families(1, seed=0)[0].configs[0]
    configs = turned_configs(base, 200, g, math.radians(80.0), 0.1)
    turns = np.array([[_angle(c[i], base[i]) for i in range(2)] for c in configs])
    shifts = np.array([[float((c[i].position - base[i].position).abs().max()) for i in range(2)] for c in configs])
    assert turns.max() <= math.radians(40.0) + 1e-9 and turns.max() > math.radians(35.0)
    assert shifts.max() <= 0.1 + 1e-12
    assert abs(np.corrcoef(turns[:, 0], turns[:, 1])[0, 1]) < 0.2  # independent frames


def test_frames_pairs_turned_keep_the_geometry_and_differ_by_bounded_turns():
    src, tgt = FramesPairs(max_turn_deg=80.0)(50, np.random.default_rng(0))
    assert src.shape == tgt.shape == (50, 10, 2)
    # each frame's keypoints: origin then +-0.1 along its axes; the origin moves by at most 0.1 per axis
    assert np.abs(src[:, [0, 5]] - tgt[:, [0, 5]]).max() <= 0.2 + 1e-12
    heading = lambda kp, i: np.arctan2(kp[:, 5 * i + 1, 1] - kp[:, 5 * i, 1], kp[:, 5 * i + 1, 0] - kp[:, 5 * i, 0])  # noqa: E731
    for i in range(2):
        d = np.abs(np.angle(np.exp(1j * (heading(src, i) - heading(tgt, i)))))
        assert d.max() <= math.radians(80.0) + 1e-9
    free_src, free_tgt = FramesPairs()(50, np.random.default_rng(0))  # independent configurations: far apart
    assert np.median(np.abs(free_src[:, 0] - free_tgt[:, 0]).max(-1)) > 0.3
    with pytest.raises(ValueError, match="max_turn_deg"):
        FramesPairs(max_turn_deg=-1.0)


def test_distillation_targets_come_from_the_teacher_given():
    from kpflow.data.keypoint_pairs import add_queries

    src, tgt = FramesPairs(max_turn_deg=80.0)(3, np.random.default_rng(1))
    pairs = add_queries(src, tgt, 8, np.random.default_rng(2), teacher=GPMap)
    for i in range(3):
        phi = GPMap().fit(torch.as_tensor(src[i]), torch.as_tensor(tgt[i]))
        with torch.no_grad():
            expected = phi(pairs.queries[i].double()).float()
        assert torch.allclose(pairs.query_targets[i], expected, atol=1e-5)
    ilwr = add_queries(src, tgt, 8, np.random.default_rng(2))  # the default teacher: ILWR, in one batch
    with torch.no_grad():
        expected = ILWRMap().fit(torch.as_tensor(src), torch.as_tensor(tgt))(ilwr.queries.double()).float()
    assert torch.allclose(ilwr.query_targets, expected, atol=1e-5)


def test_map_suite_quick_writes_one_table_against_the_authors_gp(tmp_path):
    out = tmp_path / "suite.md"
    done = subprocess.run([sys.executable, "benchmarks/map_suite.py", "--quick", "--benchmarks", "multiframe", "--out", str(out)], cwd=ROOT,
                          capture_output=True, text=True, timeout=300)  # fmt: skip
    assert done.returncode == 0, done.stderr[-3000:]
    text = out.read_text()
    summary = text.split("## Per benchmark")[0]
    rows = {
        line.split(" | ")[0][2:]: line.split(" | ")[1:]
        for line in summary.splitlines()
        if line.startswith("| ") and "---" not in line
    }
    assert rows["authors' GP"][0].strip(" |") == "1.00"  # its own reference
    assert all(float(r[0].strip(" |")) > 0 for name, r in rows.items() if name != "map")
    assert "### multiframe (72 transports per map)" in text


@pytest.mark.slow
def test_suite_recordings_round_trip_and_pair_in_the_sources_order(tmp_path):
    sys.path.insert(0, str(ROOT / "benchmarks"))
    import suite_recordings as sr

    recs = sr.load_or_record("lift", 2, 0, tmp_path)
    again = sr.load_or_record("lift", 2, 0, tmp_path)  # read back from the cache
    assert [r.index for r in recs] == [r.index for r in again]
    for a, b in zip(recs, again):
        for sa, sb in zip(a.segments, b.segments):
            assert sa.name == sb.name and sa.kind == sb.kind and np.array_equal(sa.positions, sb.positions)
            assert np.array_equal(sa.rotations, sb.rotations) and sa.half == sb.half
    source, target = sr.keypoint_pair(recs[0].segments[0], recs[1].segments[0])
    assert source.shape == target.shape == (9, 3)  # the cube's 8 corners and the grip site
    # ordered by the source's yaw: the rigid fit of the corners turns by at most 45 degrees
    from kpflow.geometry.alignment import fit_affine

    r, _ = fit_affine(torch.as_tensor(source[None, :8]), torch.as_tensor(target[None, :8]), "rigid")
    assert math.degrees(math.acos((float(torch.trace(r[0])) - 1) / 2)) <= 45.0 + 1e-6


def test_transport_into_fits_a_batch_at_once_with_the_numbers_of_one_scene_at_a_time():
    from kpflow.tasks.frames.scene import random_scenes
    from kpflow.tasks.frames.transported_demos import transport_into

    class OneAtATime(ILWRMap):
        supports_batch = False

    scenes = random_scenes(4, 60, seed=0)
    batched = transport_into(scenes, 1, ILWRMap, 0.1, 0.05)
    single = transport_into(scenes, 1, OneAtATime, 0.1, 0.05)
    assert [d.source for d in batched] == [d.source for d in single] == [0, 2, 3]
    for a, b in zip(batched, single):
        for f in ("positions", "velocities", "orientations", "std"):
            torch.testing.assert_close(getattr(a.trajectory, f), getattr(b.trajectory, f), atol=1e-8, rtol=1e-8)
        torch.testing.assert_close(a.velocities, b.velocities, atol=1e-7, rtol=1e-7)
