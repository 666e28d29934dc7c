"""DispatchCounter counts the ATen ops and the host syncs of a block, eager and compiled, and always restores the mode."""

import pytest
import torch as th

from sb3_dsslac.engine.dispatch import DispatchCounter, optimizer_step_tensors
from tests.synthetic_envs import HazardPointEnv
from tests.test_dsslac import SMALL_POLICY, small_model


def dispatch_modes_active() -> int:
    return th._C._len_torch_dispatch_stack()


def test_counts_a_matmul_and_an_add_as_two_ops_and_no_sync() -> None:
    a, b, c = th.randn(3, 4), th.randn(4, 5), th.randn(5)
    with DispatchCounter() as counter:
        a @ b + c
    assert counter.ops == 2
    assert dict(counter.op_counts) == {"aten.mm": 1, "aten.add": 1}
    assert counter.syncs == 0


def test_views_are_counted_apart_from_the_ops_that_launch_kernels() -> None:
    a, b = th.randn(3, 4), th.randn(5, 4)
    with DispatchCounter() as counter:
        y = th.nn.functional.linear(a, b)  # t (a view) and mm
        y.view(15)[2:].unsqueeze(0).add(1.0)  # three views and an add
    assert counter.ops == 6
    assert (counter.view_ops, counter.kernel_ops) == (4, 2)


def test_every_value_read_is_one_sync() -> None:
    x = th.tensor([1.5])
    with DispatchCounter() as counter:
        x.item()
        float(x)
        bool(x > 0)
    assert counter.syncs == 3
    assert counter.top(1) == [("aten._local_scalar_dense", 3)]
    assert counter.ops == 4  # and the comparison


def test_reads_of_ignored_tensors_and_their_views_are_not_syncs() -> None:
    step, other = th.tensor([3.0, 4.0]), th.tensor(1.0)
    with DispatchCounter(ignore_sync_of=[step]) as counter:
        step[0].item()  # a view: same memory, another tensor
        float(step[:1])
        other.item()
    assert (counter.syncs, counter.ignored_syncs) == (1, 2)
    assert counter.op_counts["aten._local_scalar_dense"] == 3


def test_counts_add_up_and_nested_counters_both_count() -> None:
    x = th.randn(4)
    outer = DispatchCounter()
    with outer:
        x.sin()
        with DispatchCounter() as inner:
            x.cos().sum().item()
    with outer:
        x.exp()
    assert (inner.ops, inner.syncs) == (3, 1)
    assert (outer.ops, outer.syncs) == (5, 1)
    assert dispatch_modes_active() == 0


def test_an_exception_inside_restores_the_mode() -> None:
    counter = DispatchCounter()
    with pytest.raises(RuntimeError, match="cannot be multiplied"), counter:
        th.randn(2, 3) @ th.randn(2, 3)
    assert dispatch_modes_active() == 0
    th.randn(2).sin()
    assert counter.ops == 3  # the two randn and the failed mm, nothing after the block


def test_compiled_code_runs_compiled_inside_the_counter() -> None:
    graphs = []

    def fused_backend(graph: th.fx.GraphModule, example_inputs: list[th.Tensor]):
        graphs.append(graph)
        return lambda x: (th.ops.aten.mul(x, 3.0),)  # stands for a compiled graph: one op whatever the graph held

    x = th.randn(8)
    compiled = th.compile(lambda x: ((x + 1.0) * 2.0 - 2.0) * 1.5, backend=fused_backend, dynamic=False)
    with DispatchCounter() as counter:
        out = compiled(x)
    th.testing.assert_close(out, x * 3.0)
    assert len(graphs) == 1  # Dynamo compiled inside the counter instead of falling back to eager
    assert counter.top() == [("aten.mul", 1)]  # nothing of the tracing, only what the compiled artifact dispatched


def test_adams_step_reads_can_be_left_out_of_an_update() -> None:
    th.set_num_threads(1)
    # Adam's for-loop implementation reads each step counter on the host (the default fused kernel does not)
    policy_kwargs = {**SMALL_POLICY, "optimizer_kwargs": {"foreach": False}}
    env = HazardPointEnv(obs_type="state")
    model = small_model(env, learning_starts=40, latent_pretrain_steps=1, gradient_steps=1, policy_kwargs=policy_kwargs)
    model.learn(50)  # warm-up data, the pre-training and a first update: every optimizer has its state
    steps = optimizer_step_tensors(model)
    optimizers = [model.policy.latent_optimizer, model.policy.actor_optimizer, model.policy.critic_optimizer]
    optimizers += [model.policy.cost_critic_optimizer, model.ent_coef_optimizer]
    assert len(steps) == sum(len(optimizer.state) for optimizer in optimizers) > 0
    with DispatchCounter(ignore_sync_of=steps) as counter:
        model.train(2, model.batch_size)
    with DispatchCounter() as everything:
        model.train(2, model.batch_size)
    assert counter.ops > 100 and counter.ignored_syncs > 0
    assert everything.syncs == counter.syncs + counter.ignored_syncs
