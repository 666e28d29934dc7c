"""The beliefs picture: an episode as the pixel agent filtered it, and the ``beliefs`` command."""

from pathlib import Path

import numpy as np
import pytest
import torch as th

from sb3_dsslac.app.beliefs import _pick_steps, episode_beliefs, mean_cost_probabilities, plot_beliefs
from sb3_dsslac.app.cli import main
from sb3_dsslac.app.rollouts import evaluate
from tests.synthetic_envs import HazardPointEnv
from tests.test_cli import TINY_ENV, run_train
from tests.test_dsslac import SMALL_POLICY, small_model


@pytest.fixture(scope="module")
def pixel_model():
    policy_kwargs = {**SMALL_POLICY, "image_channels": (4, 8, 8, 16)}
    model = small_model(HazardPointEnv(obs_type="pixels"), seed=3, policy_kwargs=policy_kwargs)
    model.learn(80)
    return model


def test_the_episode_is_the_one_evaluate_runs(pixel_model) -> None:
    beliefs = episode_beliefs(pixel_model, TINY_ENV, seed=5)
    steps = len(beliefs.costs)
    assert steps == 30  # the env's episode
    assert beliefs.frames.shape == beliefs.reconstructions.shape == (steps + 1, 32, 32, 3)
    assert beliefs.frames.dtype == beliefs.reconstructions.dtype == np.uint8
    assert beliefs.cost_probabilities.shape == beliefs.rewards.shape == (steps,)
    assert ((beliefs.cost_probabilities >= 0) & (beliefs.cost_probabilities <= 1)).all()
    # Acting with the filter's means, the recorder takes the very steps of a deterministic evaluation episode
    results = evaluate(pixel_model, TINY_ENV, episodes=1, deterministic=True, seed=5, obs_type="pixels")
    assert results.lengths[0] == steps
    assert results.rewards[0] == pytest.approx(beliefs.rewards.sum(), abs=1e-5)
    assert results.costs[0] == pytest.approx(beliefs.costs.sum())
    assert episode_beliefs(pixel_model, TINY_ENV, seed=5, max_steps=7).costs.shape == (7,)


def test_reconstructions_and_cost_probabilities_come_from_the_latent_model(pixel_model) -> None:
    beliefs = episode_beliefs(pixel_model, TINY_ENV, seed=1, max_steps=4)
    policy = pixel_model.policy
    # Re-filter the recorded frames with the recorded actions: the first two beliefs give the first probability
    frames = th.as_tensor(beliefs.frames[:2]).permute(0, 3, 1, 2)
    z2, action, _ = policy.initial_state(1)
    with th.no_grad():
        z0, z2 = policy.belief_step(frames[:1], z2, action, th.ones(1, dtype=th.bool), True)
        action = policy.actor(z0, deterministic=True)
        z1, _ = policy.belief_step(frames[1:], z2, action, th.zeros(1, dtype=th.bool), True)
        expected = th.sigmoid(policy.latent.cost_decoder(th.cat([z0, action, z1], dim=-1))).item()
        reconstruction = policy.latent.decode(z0.unsqueeze(1))[0, 0].clamp(0, 1).mul(255).round().permute(1, 2, 0)
    assert beliefs.cost_probabilities[0] == pytest.approx(expected, rel=1e-5)
    np.testing.assert_array_equal(beliefs.reconstructions[0], reconstruction.to(th.uint8).numpy())


def test_picked_steps_include_costly_ones() -> None:
    costs = np.zeros(100)
    costs[[13, 14, 71]] = 1.0
    picks = _pick_steps(costs, 8)
    assert len(picks) == 8 and (np.diff(picks) > 0).all()
    assert {13, 71} <= set(picks.tolist())
    assert _pick_steps(np.zeros(3), 10).tolist() == [0, 1, 2]


def test_plot_and_mean_probabilities(pixel_model, tmp_path: Path) -> None:
    beliefs = episode_beliefs(pixel_model, TINY_ENV, seed=0)
    path = plot_beliefs(beliefs, tmp_path / "sub" / "beliefs.png", n_frames=6)
    assert path.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    on_costly, on_free = mean_cost_probabilities(beliefs)
    costly = beliefs.costs > 0
    assert on_free == pytest.approx(beliefs.cost_probabilities[~costly].mean())
    assert np.isnan(on_costly) == (not costly.any())


def test_beliefs_command(tmp_path: Path, capsys) -> None:
    run = tmp_path / "pixels"
    assert run_train(run, "--sim-steps=60", "--eval-every=60", "--obs-type=pixels") == 0
    capsys.readouterr()
    assert main(["beliefs", str(run / "model.zip"), "--steps", "12", "--frames", "4", "--out", str(tmp_path / "b.png")]) == 0
    printed = capsys.readouterr().out
    assert "12 steps" in printed and "mean predicted p(cost)" in printed
    assert (tmp_path / "b.png").is_file()


def test_beliefs_needs_an_image_agent(tmp_path: Path, capsys) -> None:
    run = tmp_path / "state"
    assert run_train(run, "--sim-steps=60", "--eval-every=60") == 0
    assert main(["beliefs", str(run / "model.zip"), "--out", str(tmp_path / "b.png")]) == 2
    assert "trained on images" in capsys.readouterr().err
    assert main(["beliefs", str(tmp_path / "missing.zip")]) == 2
