"""Placement sampling and the state vector's lidar, by Safety-Gym's rules (docs/safety_envs.md)."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from safety_envs import make_env
from safety_envs.layout import ResamplingError, sample_layout, sample_position, shrink

GOAL2 = [("robot", 0.4), ("goal", 0.305)] + [(f"hazard{i}", 0.18) for i in range(10)] + [(f"vase{i}", 0.15) for i in range(10)]


@settings(max_examples=30, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), half=st.sampled_from([1.5, 2.0]))
def test_layout_respects_region_and_keepouts(seed, half):
    extents = (-half, -half, half, half)
    layout = sample_layout(np.random.default_rng(seed), GOAL2, extents)
    assert list(layout) == [name for name, _ in GOAL2]
    keepouts = dict(GOAL2)
    for name, xy in layout.items():
        xmin, ymin, xmax, ymax = shrink(extents, keepouts[name])
        assert xmin <= xy[0] <= xmax and ymin <= xy[1] <= ymax
    names = list(layout)
    for i, a in enumerate(names):
        for b in names[:i]:
            assert np.linalg.norm(layout[a] - layout[b]) >= keepouts[a] + keepouts[b]


def test_impossible_layout_raises():
    crowded = [(f"o{i}", 0.5) for i in range(5)]
    with pytest.raises(ResamplingError):
        sample_layout(np.random.default_rng(0), crowded, (-1, -1, 1, 1), max_layouts=20)
    others = np.zeros((1, 2))
    assert sample_position(np.random.default_rng(0), 0.5, (-1, -1, 1, 1), others, np.array([1.0]), max_draws=500) is None


def test_same_seed_same_layout():
    a = sample_layout(np.random.default_rng(5), GOAL2, (-2, -2, 2, 2))
    b = sample_layout(np.random.default_rng(5), GOAL2, (-2, -2, 2, 2))
    assert all(np.array_equal(a[k], b[k]) for k in a)


def test_lidar_bins_in_robot_frame():
    env = make_env("Point", "Goal", 1, obs_type="state")
    far = np.stack([np.full(8, 50.0), np.arange(8.0)], axis=1)
    hazards = far.copy()
    hazards[0] = (-1.5, 0.0)  # behind the robot at 1.5 m
    hazards[1] = (-2.0, 0.0)  # behind, further: the bin keeps the nearest
    state, _ = env.reset(
        seed=0,
        options={"robot_xy": (0, 0), "robot_yaw": 0.0, "goal_xy": (0.0, 1.5), "hazards_xy": hazards, "vases_xy": [(50, 50)]},
    )
    goal = state[env.state_slices["goal_lidar"]]
    expected = np.zeros(16)
    expected[[3, 4]] = 0.5  # +y is 90 degrees left: bin 4, aliased into bin 3; (3 - 1.5) / 3 = 0.5
    np.testing.assert_allclose(goal, expected, atol=1e-6)
    hazard = state[env.state_slices["hazards_lidar"]]
    expected = np.zeros(16)
    expected[[7, 8]] = 0.5  # 180 degrees: bin 8, aliased into bin 7
    np.testing.assert_allclose(hazard, expected, atol=1e-6)
    assert not state[env.state_slices["vases_lidar"]].any()  # beyond 3 m
    # turning the robot by +90 degrees puts the goal straight ahead: bin 0 (and bin 15 by aliasing)
    state, _ = env.reset(seed=0, options={"robot_xy": (0, 0), "robot_yaw": np.pi / 2, "goal_xy": (0.0, 1.5)})
    goal = state[env.state_slices["goal_lidar"]]
    assert goal[0] == pytest.approx(0.5, abs=1e-6) and goal.argmax() in (0, 15) and goal[1:15].max() < 1e-6
