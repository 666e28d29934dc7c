import pytest
import torch

from sb3_dsslac.nn.fused_rollout import posterior_steps
from sb3_dsslac.nn.latent import LatentModel


def rollout_inputs(model: LatentModel, batch: int, steps: int) -> tuple[torch.Tensor, ...]:
    """Features of frames 1..T and actions (both with gradients), frame 0's latent from the model, and the noise."""
    features = torch.randn(batch, steps, model.feature_dim, dtype=torch.float64, requires_grad=True)
    actions = torch.randn(batch, steps, model.action_dim, dtype=torch.float64, requires_grad=True)
    first_feature = torch.randn(batch, model.feature_dim, dtype=torch.float64, requires_grad=True)
    z1_mean, z1_std = model.z1_posterior_init(first_feature)
    z1 = z1_mean + z1_std * torch.randn_like(z1_mean)
    z2_mean, z2_std = model.z2_init(z1)
    first = (z1_mean, z1_std, z1, z2_mean + z2_std * torch.randn_like(z2_mean))
    z1_noise = torch.randn(steps, batch, model.z1_dim, dtype=torch.float64)
    z2_noise = torch.randn(steps, batch, model.z2_dim, dtype=torch.float64)
    return features, actions, first_feature, first, z1_noise, z2_noise


@pytest.mark.parametrize("hidden_units, steps", [((7, 7), 4), ((5,), 1), ((6, 4, 5), 3)])
def test_fused_rollout_matches_autograd_step_by_step(hidden_units, steps) -> None:
    torch.manual_seed(0)
    model = LatentModel((9,), 2, feature_dim=6, z1_dim=3, z2_dim=4, hidden_units=hidden_units).double()
    features, actions, first_feature, first, z1_noise, z2_noise = rollout_inputs(model, batch=5, steps=steps)
    mlps = (model.z1_posterior_init, model.z2_init, model.z1_posterior, model.z2_transition)
    inputs = [features, actions, first_feature, *(param for mlp in mlps for param in mlp.parameters())]

    def outputs_and_grads(rollout: tuple[torch.Tensor, ...]) -> tuple[list[torch.Tensor], list[torch.Tensor]]:
        assert all(value.shape[:2] == (5, steps + 1) for value in rollout)
        weights = [torch.linspace(-1.0, 2.0, value.numel(), dtype=torch.float64).view_as(value) for value in rollout]
        loss = sum((value * weight).sum() for value, weight in zip(rollout, weights, strict=True))
        return list(rollout), list(torch.autograd.grad(loss, inputs, retain_graph=True, materialize_grads=True))

    fused = outputs_and_grads(
        posterior_steps(features, actions, first, z1_noise, z2_noise, model.z1_posterior, model.z2_transition)
    )
    reference = outputs_and_grads(model._posterior_steps(features, actions, first, z1_noise, z2_noise))
    for fused_values, reference_values in zip(fused, reference, strict=True):
        for fused_value, reference_value in zip(fused_values, reference_values, strict=True):
            torch.testing.assert_close(fused_value, reference_value, rtol=1e-10, atol=1e-12)
    # The gradient reaches every weight of both MLPs, the features, the actions and frame 0's latent
    assert all(grad.abs().sum() > 0 for grad in fused[1])


def test_fused_rollout_without_gradients_gives_the_same_latents() -> None:
    torch.manual_seed(1)
    model = LatentModel((9,), 2, feature_dim=6, z1_dim=3, z2_dim=4, hidden_units=(8, 8)).double()
    features, actions, _, first, z1_noise, z2_noise = rollout_inputs(model, batch=3, steps=5)
    recorded = posterior_steps(features, actions, first, z1_noise, z2_noise, model.z1_posterior, model.z2_transition)
    with torch.no_grad():
        unrecorded = posterior_steps(features, actions, first, z1_noise, z2_noise, model.z1_posterior, model.z2_transition)
    assert recorded[0].grad_fn is not None and unrecorded[0].grad_fn is None
    for with_grad, without_grad in zip(recorded, unrecorded, strict=True):
        torch.testing.assert_close(with_grad.detach(), without_grad, rtol=0, atol=0)


@pytest.mark.parametrize("bounds", [{}, {"min_std": 0.1, "max_std": 0.7, "mean_bound": 0.3}], ids=["thesis", "bounded"])
def test_latent_loss_is_the_same_through_the_fused_and_the_autograd_rollout(bounds) -> None:
    # Bounded, the means' tanh and the stds' sigmoid take the hand-written backward pass as autograd does
    torch.manual_seed(2)
    model = LatentModel((3, 32, 32), 2, feature_dim=16, z1_dim=4, z2_dim=8, hidden_units=(16, 16), **bounds).double()
    observations = torch.rand(2, 4, 3, 32, 32, dtype=torch.float64)
    actions, rewards = torch.rand(2, 3, 2, dtype=torch.float64) * 2 - 1, torch.randn(2, 3, dtype=torch.float64)
    costs, terminated = (rewards > 0).double(), torch.zeros(2, 3, dtype=torch.float64)

    def loss_and_grads(compiling: bool) -> tuple[torch.Tensor, list[torch.Tensor]]:
        torch.manual_seed(3)
        if compiling:  # what the loss runs while torch.compile traces it: autograd records each step
            with pytest.MonkeyPatch.context() as patch:
                patch.setattr(torch.compiler, "is_compiling", lambda: True)
                loss, info = model.loss(observations, actions, rewards, costs, terminated)
        else:
            loss, info = model.loss(observations, actions, rewards, costs, terminated)
        if bounds:
            assert info["z_abs_max"] > 0.2  # the means' tanh is well away from the identity
        return loss, list(torch.autograd.grad(loss, list(model.parameters())))

    fused_loss, fused_grads = loss_and_grads(compiling=False)
    reference_loss, reference_grads = loss_and_grads(compiling=True)
    torch.testing.assert_close(fused_loss, reference_loss)
    for fused_grad, reference_grad in zip(fused_grads, reference_grads, strict=True):
        torch.testing.assert_close(fused_grad, reference_grad, rtol=1e-9, atol=1e-9)


def test_under_bfloat16_autocast_the_rollout_runs_fused_in_float32() -> None:
    torch.manual_seed(4)
    model = LatentModel((9,), 2, feature_dim=6, z1_dim=3, z2_dim=4, hidden_units=(8, 8))
    features = torch.randn(2, 5, 6, requires_grad=True)
    with torch.autocast("cpu", dtype=torch.bfloat16):
        rollout = model.posterior(features.bfloat16(), torch.rand(2, 4, 2))
    assert all(field.dtype == torch.float32 for field in rollout)
    assert type(rollout.z2.grad_fn).__name__ == "_PosteriorStepsBackward"
    rollout.z2.sum().backward()
    assert features.grad is not None and model.z1_posterior_init.net[0].weight.grad is not None
