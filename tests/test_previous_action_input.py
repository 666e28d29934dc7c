"""``previous_action_input``: the actor and critics see ``[z_t, a_{t-1}]`` when acting, in the update and after a reload."""

import numpy as np
import pytest
import torch as th

from sb3_dsslac import DSSLAC
from tests.synthetic_envs import HazardPointEnv
from tests.test_dsslac import SMALL, SMALL_POLICY, small_model

WITH_PREVIOUS_ACTION = {**SMALL_POLICY, "previous_action_input": True}


def model_with_previous_action(**overrides) -> DSSLAC:
    transitions = SMALL["sequence_length"] - 1
    return small_model(HazardPointEnv(), policy_kwargs=WITH_PREVIOUS_ACTION, actor_critic_transitions=transitions, **overrides)


def record_inputs(module: th.nn.Module) -> list[tuple[th.Tensor, ...]]:
    """The positional inputs of every later forward call of ``module``."""
    seen: list[tuple[th.Tensor, ...]] = []
    module.register_forward_pre_hook(lambda _module, args: seen.append(tuple(arg.detach().clone() for arg in args)))
    return seen


def test_the_networks_take_the_belief_and_the_action() -> None:
    policy = model_with_previous_action().policy
    z_dim, action_dim = policy.latent.z_dim, policy.action_dim
    assert policy.actor.net[0].in_features == z_dim + action_dim
    assert policy.critic.weights[0].shape[1] == z_dim + 2 * action_dim  # [z, a_prev] and the action valued
    assert policy.cost_critic.cosine_net.out_features == z_dim + 2 * action_dim
    plain = small_model(HazardPointEnv()).policy
    assert plain.actor.net[0].in_features == z_dim


def test_predict_gives_the_actor_the_previous_action_and_zero_at_an_episode_start() -> None:
    model = model_with_previous_action()
    seen = record_inputs(model.policy.actor)
    observation = np.zeros((1, 4), dtype=np.float32)
    previous = np.array([[0.25, -0.75]], dtype=np.float32)
    state = (np.zeros((1, model.policy.z2_dim), dtype=np.float32), previous)
    model.policy.predict(observation, state, episode_start=np.array([False]), deterministic=True)
    model.policy.predict(observation, state, episode_start=np.array([True]), deterministic=True)
    z_dim = model.policy.latent.z_dim
    th.testing.assert_close(seen[0][0][:, z_dim:], th.as_tensor(previous))
    th.testing.assert_close(seen[1][0][:, z_dim:], th.zeros(1, 2))


def test_the_rollouts_act_on_the_action_taken_before() -> None:
    model = model_with_previous_action(learning_starts=5, latent_pretrain_steps=1)
    seen = record_inputs(model.policy.actor)
    taken: list[th.Tensor] = []
    model.policy.actor.register_forward_hook(lambda _module, _args, output: taken.append(output.detach().clone()))
    model.learn(70)  # episodes of 30 steps; the actor acts from step 5
    z_dim = model.policy.latent.z_dim
    assert len(seen) == len(taken) == 65
    th.testing.assert_close(seen[0][0][:, z_dim:], th.as_tensor(model.replay_buffer.actions[4]))  # a warm-up action
    for step in range(6, 70):
        previous = th.zeros(1, 2) if step % 30 == 0 else taken[step - 6]
        th.testing.assert_close(seen[step - 5][0][:, z_dim:], previous)


def test_the_update_pairs_each_belief_with_the_action_before_it() -> None:
    model = model_with_previous_action()
    model.learn(45)
    seen = record_inputs(model.policy.critic)
    k, length = SMALL["sequence_length"] - 1, SMALL["sequence_length"]
    latents = th.randn(8, length + 1, model.policy.latent.z_dim)
    batch = model.replay_buffer.gather(model.replay_buffer.sample_indices(1, 8)[0])
    model.updates.step.actor_critic_update(batch, latents)
    states, actions = seen[0]
    # frames L-k .. L-1, each with the action that led to it; the actions valued are the ones taken from them
    expected = th.cat([latents[:, -k - 1 : -1], batch.actions[:, -k - 1 : -1]], dim=-1).reshape(8 * k, -1)
    th.testing.assert_close(states, expected)
    th.testing.assert_close(actions, batch.actions[:, -k:].reshape(8 * k, -1))
    transitions = model.updates.step.transitions(batch, latents)
    next_states = th.cat([latents[:, -k:], batch.actions[:, -k:]], dim=-1).reshape(8 * k, -1)
    th.testing.assert_close(transitions.next_latents, next_states)


def test_every_transition_needs_its_previous_action_in_the_window() -> None:
    with pytest.raises(ValueError, match=r"sequence_length - 1 = 2\] with previous_action_input"):
        small_model(HazardPointEnv(), policy_kwargs=WITH_PREVIOUS_ACTION, actor_critic_transitions=SMALL["sequence_length"])


def test_a_saved_agent_keeps_its_input(tmp_path) -> None:
    model = model_with_previous_action()
    model.learn(45)
    model.save(tmp_path / "agent.zip")
    loaded = DSSLAC.load(tmp_path / "agent.zip")
    assert loaded.policy.previous_action_input
    observation = np.zeros((1, 4), dtype=np.float32)
    state = (np.zeros((1, model.policy.z2_dim), dtype=np.float32), np.array([[0.5, 0.5]], dtype=np.float32))
    expected, _ = model.policy.predict(observation, state, np.array([False]), deterministic=True)
    actions, _ = loaded.policy.predict(observation, state, np.array([False]), deterministic=True)
    np.testing.assert_allclose(actions, expected, rtol=1e-6)
