"""``actor_critic_memory``: a GRU over the beliefs that the actor and critics take beside them, carried when acting, run
over each window in the update, trained by the reward critic alone, and kept by save/load."""

import numpy as np
import pytest
import torch as th

from sb3_dsslac import DSSLAC
from sb3_dsslac.nn.memory import BeliefMemory
from tests.synthetic_envs import HazardPointEnv
from tests.test_dsslac import SMALL, SMALL_POLICY, small_model
from tests.test_previous_action_input import record_inputs

MEMORY = 8
WITH_MEMORY = {**SMALL_POLICY, "actor_critic_memory": MEMORY}


def model_with_memory(**overrides) -> DSSLAC:
    transitions = SMALL["sequence_length"] - 1
    return small_model(HazardPointEnv(), policy_kwargs=WITH_MEMORY, actor_critic_transitions=transitions, **overrides)


def test_unroll_is_the_step_repeated_from_zero() -> None:
    th.manual_seed(0)
    memory = BeliefMemory(z_dim=5, action_dim=2, memory_dim=MEMORY)
    z, actions = th.randn(3, 4, 5), th.randn(3, 4, 2)
    unrolled = memory.unroll(z, actions)
    state = th.zeros(3, MEMORY)
    for step in range(4):
        state = memory(z[:, step], actions[:, step], state)
        th.testing.assert_close(unrolled[:, step], state)


def test_the_networks_take_the_belief_and_the_memory_and_the_reward_critic_trains_it() -> None:
    policy = model_with_memory().policy
    z_dim = policy.latent.z_dim
    assert policy.actor.net[0].in_features == z_dim + MEMORY
    assert policy.critic.weights[0].shape[1] == z_dim + MEMORY + policy.action_dim
    assert policy.cost_critic.cosine_net.out_features == z_dim + MEMORY + policy.action_dim
    memory_params = {id(param) for param in policy.memory.parameters()}
    optimizer_params = {
        name: {id(param) for param in getattr(policy, name).param_groups[0]["params"]}
        for name in ("critic_optimizer", "cost_critic_optimizer", "actor_optimizer", "latent_optimizer")
    }
    assert memory_params <= optimizer_params["critic_optimizer"]
    for name in ("cost_critic_optimizer", "actor_optimizer", "latent_optimizer"):
        assert not memory_params & optimizer_params[name], name
    assert small_model(HazardPointEnv()).policy.memory is None


def test_predict_carries_the_memory_and_an_episode_start_clears_it() -> None:
    model = model_with_memory()
    policy = model.policy
    observation = np.zeros((1, 4), dtype=np.float32)
    _, state = policy.predict(observation, deterministic=True)
    assert [part.shape for part in state] == [(1, policy.z2_dim), (1, policy.action_dim), (1, MEMORY)]
    assert np.abs(state[2]).max() > 0
    carried = (state[0], state[1], state[2] + 1.0)
    _, after = policy.predict(observation, state, np.array([False]), deterministic=True)
    _, after_other = policy.predict(observation, carried, np.array([False]), deterministic=True)
    assert not np.allclose(after[2], after_other[2])  # the memory carried in counts
    _, restarted = policy.predict(observation, carried, np.array([True]), deterministic=True)
    np.testing.assert_allclose(restarted[2], state[2], rtol=1e-6)  # a start forgets it, as the first call
    with pytest.raises(ValueError, match="memory"):
        policy.predict(observation, state[:2], np.array([False]))


def test_the_rollouts_act_on_the_memory_of_their_episode() -> None:
    model = model_with_memory(learning_starts=5, latent_pretrain_steps=1)
    policy = model.policy
    seen = record_inputs(policy.actor)
    steps: list[tuple[th.Tensor, ...]] = []

    def record_acting(_module: th.nn.Module, args: tuple[th.Tensor, ...], output: th.Tensor) -> None:
        if th.is_inference_mode_enabled():  # acting, not the update's windows
            steps.append((*(arg.clone() for arg in args), output.clone()))

    policy.memory.register_forward_hook(record_acting)
    model.learn(70)  # episodes of 30 steps; the memory runs from step 0, the actor acts from step 5
    assert len(steps) == 70 and len(seen) == 65
    for step in range(1, 70):
        z, action_prev, memory_prev, memory = steps[step]
        if step % 30 == 0:  # an episode's first belief: no previous action, no memory
            assert not action_prev.any() and not memory_prev.any()
        else:  # the action taken and the memory left by the step before
            record = step - 1 + (step - 1) // 30  # each episode's final frame takes a record of its own
            th.testing.assert_close(action_prev, th.as_tensor(model.replay_buffer.actions[record]))
            th.testing.assert_close(memory_prev, steps[step - 1][3])
        if step >= 5:  # the actor takes the belief and the memory after it
            th.testing.assert_close(seen[step - 5][0], th.cat([z, memory], dim=-1))


def test_the_update_runs_the_memory_over_each_window_and_only_the_reward_critic_moves_it() -> None:
    model = model_with_memory()
    model.learn(45)
    policy, step = model.policy, model.updates.step
    seen = record_inputs(policy.critic)
    k, length = SMALL["sequence_length"] - 1, SMALL["sequence_length"]
    latents = th.randn(8, length + 1, policy.latent.z_dim)
    batch = model.replay_buffer.gather(model.replay_buffer.sample_indices(1, 8)[0])
    with th.no_grad():
        memory = policy.memory.unroll(latents[:, 1:], batch.actions)  # frames 1..L, from zero before frame 1
    states = th.cat([latents[:, 1:], memory], dim=-1)
    transitions = step.transitions(batch, latents)
    th.testing.assert_close(transitions.latents, states[:, -k - 1 : -1].reshape(8 * k, -1))
    th.testing.assert_close(transitions.next_latents, states[:, -k:].reshape(8 * k, -1))
    assert transitions.latents.requires_grad and not transitions.next_latents.requires_grad
    # The reward critic's step moves the memory; with its step size at zero nothing else does
    before = [param.detach().clone() for param in policy.memory.parameters()]
    step.actor_critic_update(batch, latents)
    assert any(not th.equal(param, old) for param, old in zip(policy.memory.parameters(), before, strict=True))
    th.testing.assert_close(seen[0][0], transitions.latents.detach())
    policy.critic_optimizer.param_groups[0]["lr"] = 0.0  # the eager step's size; a compiled step reads the tensor
    step.learning_rates[policy.critic_optimizer].zero_()
    before = [param.detach().clone() for param in policy.memory.parameters()]
    actor_before = [param.detach().clone() for param in policy.actor.parameters()]
    step.actor_critic_update(batch, latents)
    for param, old in zip(policy.memory.parameters(), before, strict=True):
        assert th.equal(param, old)
    assert any(not th.equal(param, old) for param, old in zip(policy.actor.parameters(), actor_before, strict=True))


def test_every_learned_transition_needs_a_frame_of_the_window_before_it() -> None:
    with pytest.raises(ValueError, match=r"sequence_length - 1 = 2\] with actor_critic_memory"):
        small_model(HazardPointEnv(), policy_kwargs=WITH_MEMORY, actor_critic_transitions=SMALL["sequence_length"])
    with pytest.raises(ValueError, match="actor_critic_memory must be"):
        small_model(HazardPointEnv(), policy_kwargs={**SMALL_POLICY, "actor_critic_memory": -1})


def test_a_saved_agent_keeps_its_memory(tmp_path) -> None:
    model = model_with_memory()
    model.learn(45)
    model.save(tmp_path / "agent.zip")
    loaded = DSSLAC.load(tmp_path / "agent.zip")
    assert loaded.policy.actor_critic_memory == MEMORY
    observation = np.zeros((1, 4), dtype=np.float32)
    state = (
        np.zeros((1, model.policy.z2_dim), dtype=np.float32),
        np.array([[0.5, 0.5]], dtype=np.float32),
        np.full((1, MEMORY), 0.3, dtype=np.float32),
    )
    expected, expected_state = model.policy.predict(observation, state, np.array([False]), deterministic=True)
    actions, loaded_state = loaded.policy.predict(observation, state, np.array([False]), deterministic=True)
    np.testing.assert_allclose(actions, expected, rtol=1e-6)
    np.testing.assert_allclose(loaded_state[2], expected_state[2], rtol=1e-6)
