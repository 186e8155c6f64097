"""Trajectories: eq. 20 path (speed, layers, range), cyclic, random, file."""

from __future__ import annotations

import numpy as np
import pytest
from numpy.testing import assert_allclose

from gateway.errors import ConfigError
from sim_plc.config import (
    CyclicConfig,
    FileTrajectoryConfig,
    PaperPathConfig,
    RandomConfig,
)
from sim_plc.trajectories import (
    FileTrajectory,
    PaperPath,
    cyclic_motion,
    file_trajectory,
    random_motion,
    speed_profile,
)

HOME = np.array([0.0, 0.0, 1.5, 0.0, 0.0, 0.0])


@pytest.fixture(scope="module")
def paper() -> PaperPath:
    return PaperPath(PaperPathConfig(), HOME)


def test_paper_path_speed_is_constant_between_ramps(paper: PaperPath) -> None:
    for start, seg in zip(paper.starts, paper.segments, strict=False):
        if seg.duration - 2 * seg.ramp < 0.1:  # the 20 mm lift is all ramp
            continue
        t = np.linspace(start + seg.ramp + 0.01, start + seg.duration - seg.ramp - 0.01, 2000)
        speed = np.linalg.norm(paper.evaluate(t).velocity[:, :3], axis=1)
        assert_allclose(speed, 0.04, rtol=1e-9)


def test_paper_path_has_two_printed_layers_one_lift_apart(paper: PaperPath) -> None:
    printed = [s for s in paper.segments if s.printing]
    assert len(printed) == 2
    l1, l2 = printed
    assert l1.length == pytest.approx(l2.length, rel=1e-9)
    # eq. 20 over u in [0, 15]: ~1.95 m per layer, ~49 s per layer at 0.04 m/s
    assert 1.9 < l1.length < 2.0
    end1 = paper.evaluate(np.array([paper.starts[1] - 1e-9])).pose[0]
    start2 = paper.evaluate(np.array([paper.starts[2]])).pose[0]
    assert_allclose(start2 - end1, [0, 0, 0.02, 0, 0, 0], atol=1e-9)
    assert paper.printing_time(np.array([paper.duration_s]))[0] == pytest.approx(
        l1.duration + l2.duration
    )


def test_paper_path_range_is_eq20_over_u_0_15_centred_on_home(paper: PaperPath) -> None:
    pose = paper.evaluate(np.linspace(0, paper.duration_s, 40001)).pose
    span = pose.max(axis=0) - pose.min(axis=0)
    assert_allclose(span[:3], [0.4, 0.225, 0.15 + 0.02], atol=2e-4)
    assert_allclose(0.5 * (pose.max(axis=0) + pose.min(axis=0))[:3], HOME[:3], atol=2e-4)
    assert np.all(pose[:, 3:] == 0)
    # the first point is eq. 20 at u = 0 plus the offset
    p0 = pose[0, :3] - (paper.segments[0].curve.offset)
    assert_allclose(p0, [0.2 * np.sin(5.0), 0.225, 0.0], atol=1e-12)


def test_paper_velocity_and_acceleration_are_derivatives(paper: PaperPath) -> None:
    t = np.arange(0, paper.duration_s, 0.0005)
    s = paper.evaluate(t)
    fd_v = np.gradient(s.pose, t, axis=0)[1:-1]
    fd_a = np.gradient(s.velocity, t, axis=0)[1:-1]
    assert np.max(np.abs(fd_v - s.velocity[1:-1])) < 2e-5
    assert np.max(np.abs(fd_a - s.acceleration[1:-1])) < 2e-3 * np.max(np.abs(s.acceleration))


def test_paper_path_starts_and_ends_at_rest_and_holds(paper: PaperPath) -> None:
    s = paper.evaluate(np.array([0.0, paper.duration_s, paper.duration_s + 5.0]))
    assert_allclose(s.velocity, 0.0, atol=1e-12)
    assert_allclose(s.pose[1], s.pose[2])
    assert not s.printing[2]


def test_speed_profile_reaches_length_with_ramps() -> None:
    tau = np.linspace(0, 11.0, 11001)
    s, v, _ = speed_profile(tau, 0.4, 0.04, 1.0)
    assert s[-1] == pytest.approx(0.4)
    assert v.max() == pytest.approx(0.04)
    assert_allclose(np.gradient(s, tau), v, atol=1e-6)


def test_vectorised_equals_pointwise(paper: PaperPath) -> None:
    t = np.array([0.3, 12.0, 49.5, 50.1, 77.7])
    batch = paper.evaluate(t)
    for k, tk in enumerate(t):
        one = paper.evaluate(np.array([tk]))
        assert_allclose(one.pose[0], batch.pose[k], atol=1e-12)
        assert_allclose(one.acceleration[0], batch.acceleration[k], atol=1e-12)


def test_cyclic_passes_through_the_point_in_all_six_dof() -> None:
    cfg = CyclicConfig(frequency_hz=(0.25,) * 6)
    motion = cyclic_motion(cfg, HOME)
    s = motion.evaluate(np.array([0.0, 2.0, 4.0, 1.0]))
    assert_allclose(s.pose[0], HOME, atol=1e-12)
    assert_allclose(s.pose[1], HOME, atol=1e-12)  # half a period later, moving back
    assert np.all(np.sign(s.velocity[0]) == -np.sign(s.velocity[1])[np.array(cfg.amplitude) > 0])
    assert_allclose(s.pose[3], HOME + np.array(cfg.amplitude), atol=1e-12)


def test_random_motion_is_bounded_smooth_seeded_and_reverses() -> None:
    cfg = RandomConfig(seed=3)
    motion = random_motion(cfg, HOME)
    t = np.arange(0, 120, 0.01)
    s = motion.evaluate(t)
    assert np.all(np.abs(s.pose - HOME) <= np.array(cfg.amplitude) + 1e-12)
    reversals = np.sum(np.diff(np.sign(s.velocity), axis=0) != 0, axis=0)
    assert np.all(reversals >= 4)
    again = random_motion(cfg, HOME).evaluate(t)
    assert_allclose(again.pose, s.pose)
    other = random_motion(RandomConfig(seed=4), HOME).evaluate(t)
    assert not np.allclose(other.pose, s.pose)


def test_file_trajectory_interpolates_and_holds(tmp_path) -> None:
    t = np.linspace(0, 2, 21)
    x = 0.1 * t**2
    rows = np.column_stack([t + 5.0, x, 0 * t, 1.5 + 0 * t, 0 * t, 0 * t, 0.01 * t, t > 1])
    path = tmp_path / "traj.csv"
    np.savetxt(path, rows, delimiter=",", header="t,x,y,z,rx,ry,rz,printing", comments="")
    traj = file_trajectory(FileTrajectoryConfig(path="traj.csv"), str(tmp_path))
    assert traj.duration_s == pytest.approx(2.0)
    s = traj.evaluate(np.array([0.5, 1.5, 3.0]))
    assert_allclose(s.pose[:2, 0], 0.1 * np.array([0.5, 1.5]) ** 2, atol=1e-12)
    assert_allclose(s.velocity[:2, 0], 0.2 * np.array([0.5, 1.5]), atol=1e-9)
    assert_allclose(s.velocity[2], 0.0)
    assert_allclose(s.pose[2, 0], 0.4)
    assert list(s.printing) == [False, True, False]
    assert traj.printing_time(np.array([2.0]))[0] == pytest.approx(0.95, abs=0.06)


def test_file_trajectory_errors_name_the_file(tmp_path) -> None:
    path = tmp_path / "bad.csv"
    path.write_text("t,x,y\n0,1,2\n1,2,3\n")
    with pytest.raises(ConfigError, match=r"bad\.csv"):
        FileTrajectory(path)
    with pytest.raises(ConfigError, match=r"missing\.csv"):
        FileTrajectory(tmp_path / "missing.csv")
