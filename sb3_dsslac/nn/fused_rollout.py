"""
The recurrent steps of the latent model's posterior rollout as one autograd node, with the backward pass through time
written by hand.

Recorded by autograd, each step of the rollout is two ELU MLPs (z1's posterior, z2's transition), a split, the mean's
and std's functions and a reparameterised sample per MLP, every linear layer with its own weight transpose;
backpropagating adds each weight's per-step gradients one at a time. Here the forward pass computes the same arithmetic
with each weight transposed once per rollout and the inputs that do not recur (the frames' features, the actions)
multiplied for all steps at once. The backward pass carries only the recurrent gradients step by step; the gradient of
every weight, bias, feature and action is one matrix product (or sum) over all steps. Same math, far fewer ops (2,419
to 1,658 per eager update at the thesis shapes): it exists for GPUs, which pay for every op in kernel launches when the
update is eager; a compiled update gains nothing from it.

The layout of both MLPs is ``GaussianMLP``'s: linear layers with ELU between them; the last one's output is
``[mean_raw, raw]``, made a mean and a std by the module's ``bounds`` (``GaussianBounds``). z1's posterior takes
``[feature, z2_prev, action]``, z2's transition ``[z1, z2_prev, action]``, in that column order.
"""

from typing import Any

import torch
import torch.nn.functional as F
from torch import Tensor, nn

from sb3_dsslac.nn.gaussian import GaussianBounds


def linear_layers(mlp: nn.Module) -> list[nn.Linear]:
    """The linear layers of an MLP, in order."""
    return [layer for layer in mlp.modules() if isinstance(layer, nn.Linear)]


def _elu_backward(grad: Tensor, output: Tensor) -> Tensor:
    """Gradient of ELU (alpha 1) at the input, from the gradient at and the value of its output."""
    return torch.ops.aten.elu_backward(grad, 1.0, 1.0, 1.0, True, output)


def _layer_pairs(params: list[Tensor]) -> list[tuple[Tensor, Tensor]]:
    """``[w0, b0, w1, b1, ...]`` -> ``[(w0, b0), (w1, b1), ...]``."""
    return list(zip(params[::2], params[1::2], strict=True))


def _mlp_forward(
    hidden: Tensor, layers: list[tuple[Tensor, Tensor]], kept: list[list[Tensor]], out_dim: int, bounds: GaussianBounds
) -> tuple[Tensor, Tensor, Tensor]:
    """
    One step's forward pass through an MLP from its first layer's pre-activation (B, H), noting each hidden output in
    ``kept``: the mean, the raw std and the std, each (B, out_dim).

    :param layers: the transposed weight (in, out) and the bias of each layer after the first
    """
    for layer, (weight_t, bias) in enumerate(layers):
        hidden = F.elu(hidden)
        kept[layer].append(hidden)
        hidden = torch.addmm(bias, hidden, weight_t)
    mean_raw, raw = hidden.split(out_dim, dim=1)
    mean, std = bounds(mean_raw, raw)
    return mean, raw, std


def _rollout(
    features: Tensor,
    actions: Tensor,
    first: tuple[Tensor, Tensor, Tensor, Tensor],
    z1_noise: Tensor,
    z2_noise: Tensor,
    posterior_params: list[Tensor],
    transition_params: list[Tensor],
    bounds: tuple[GaussianBounds, GaussianBounds],
    keep: bool,
) -> tuple[tuple[Tensor, ...], tuple[Tensor, ...]]:
    """
    The forward pass of ``posterior_steps`` (see there for the arguments).

    :param bounds: the ``GaussianBounds`` of z1's posterior and of z2's transition
    :param keep: also return what the backward pass needs
    :return: the outputs ``(z1_mean, z1_std, z1, z2)``, each (B, T+1, dim), and, with ``keep``, in time-major rows
        (T * B, dim): the features, the actions, z2's transition's inputs ``[z1, z2_prev]``, then per MLP its hidden
        outputs layer by layer, its mean and its raw std
    """
    batch, steps, feature_dim = features.shape
    z1_dim, z2 = z1_noise.shape[-1], first[3]
    z2_dim = z2.shape[-1]
    rows_features = features.transpose(0, 1).reshape(steps * batch, feature_dim)
    action_dim = actions.shape[-1]
    rows_actions = actions.transpose(0, 1).reshape(steps * batch, action_dim)
    # The first layers' weights by input: [feature, z2_prev, action] and [z1 and z2_prev, action]
    posterior_feature, posterior_z2, posterior_action = posterior_params[0].split([feature_dim, z2_dim, action_dim], 1)
    transition_pair, transition_action = transition_params[0].split([z1_dim + z2_dim, action_dim], 1)
    # The parts of the first layers that do not recur, for all steps at once
    posterior_inputs = torch.addmm(posterior_params[1], rows_features, posterior_feature.t())
    posterior_inputs = torch.addmm(posterior_inputs, rows_actions, posterior_action.t())
    transition_inputs = torch.addmm(transition_params[1], rows_actions, transition_action.t())
    posterior_recurrent, transition_recurrent = posterior_z2.t(), transition_pair.t()
    posterior_layers = [(weight.t(), bias) for weight, bias in _layer_pairs(posterior_params[2:])]
    transition_layers = [(weight.t(), bias) for weight, bias in _layer_pairs(transition_params[2:])]

    outputs = tuple([value] for value in first)
    posterior_hidden: list[list[Tensor]] = [[] for _ in posterior_layers]
    transition_hidden: list[list[Tensor]] = [[] for _ in transition_layers]
    posterior_mean, posterior_raw, transition_in, transition_mean, transition_raw = [], [], [], [], []
    for posterior_in, transition_in_action, z1_eps, z2_eps in zip(
        posterior_inputs.split(batch), transition_inputs.split(batch), z1_noise.unbind(0), z2_noise.unbind(0), strict=True
    ):
        pre_activation = torch.addmm(posterior_in, z2, posterior_recurrent)
        z1_mean, raw, z1_std = _mlp_forward(pre_activation, posterior_layers, posterior_hidden, z1_dim, bounds[0])
        z1 = torch.addcmul(z1_mean, z1_std, z1_eps)
        pair = torch.cat([z1, z2], dim=1)
        pre_activation = torch.addmm(transition_in_action, pair, transition_recurrent)
        z2_mean, raw2, z2_std = _mlp_forward(pre_activation, transition_layers, transition_hidden, z2_dim, bounds[1])
        z2 = torch.addcmul(z2_mean, z2_std, z2_eps)

        for output, value in zip(outputs, (z1_mean, z1_std, z1, z2), strict=True):
            output.append(value)
        posterior_mean.append(z1_mean)
        posterior_raw.append(raw)
        transition_in.append(pair)
        transition_mean.append(z2_mean)
        transition_raw.append(raw2)
    stacked = tuple(torch.stack(output, dim=1) for output in outputs)
    if not keep:
        return stacked, ()
    kept = (
        rows_features,
        rows_actions,
        torch.cat(transition_in),
        *(torch.cat(layer) for layer in posterior_hidden),
        torch.cat(posterior_mean),
        torch.cat(posterior_raw),
        *(torch.cat(layer) for layer in transition_hidden),
        torch.cat(transition_mean),
        torch.cat(transition_raw),
    )
    return stacked, kept


def _mlp_backward(grad_out: Tensor, hidden: list[Tensor], weights: list[Tensor], grads: list[list[Tensor]]) -> Tensor:
    """
    One step's backward pass through an MLP's layers after its first: from the gradient at its output to the gradient
    at its first layer's pre-activation, noting each layer's output gradient in ``grads`` (last layer first).

    :param hidden: the step's hidden outputs (B, H), layer by layer
    :param weights: the linear weights (out, in), in order (the first layer's is not used)
    """
    grads[-1].append(grad_out)
    for layer in range(len(hidden) - 1, -1, -1):
        grad_out = _elu_backward(grad_out.mm(weights[layer + 1]), hidden[layer])
        grads[layer].append(grad_out)
    return grad_out


class _PosteriorSteps(torch.autograd.Function):
    """``posterior_steps`` with the hand-written backward pass through time (module docstring)."""

    @staticmethod
    def forward(ctx: Any, features, actions, z1_mean, z1_std, z1, z2, z1_noise, z2_noise, n_posterior: int, bounds, *params):  # type: ignore[override]
        first = (z1_mean, z1_std, z1, z2)
        posterior_params, transition_params = list(params[:n_posterior]), list(params[n_posterior:])
        outputs, kept = _rollout(
            features, actions, first, z1_noise, z2_noise, posterior_params, transition_params, bounds, keep=True
        )
        ctx.bounds = bounds
        ctx.layer_counts = (n_posterior // 2, (len(params) - n_posterior) // 2)
        ctx.dims = (features.shape[0], features.shape[1], z1_noise.shape[-1], z2.shape[-1])
        ctx.save_for_backward(z1_noise, z2_noise, *kept, *params)
        return outputs

    @staticmethod
    def backward(ctx: Any, grad_z1_mean: Tensor, grad_z1_std: Tensor, grad_z1: Tensor, grad_z2: Tensor):  # type: ignore[override]
        batch, steps, z1_dim, z2_dim = ctx.dims
        n_posterior, n_transition = ctx.layer_counts
        z1_noise, z2_noise, rows_features, rows_actions, transition_in, *rest = ctx.saved_tensors
        posterior_rows = rest[: n_posterior - 1]
        posterior_hidden = [rows.split(batch) for rows in posterior_rows]
        posterior_mean, posterior_raw = (rows.split(batch) for rows in rest[n_posterior - 1 : n_posterior + 1])
        rest = rest[n_posterior + 1 :]
        transition_rows = rest[: n_transition - 1]
        transition_hidden = [rows.split(batch) for rows in transition_rows]
        transition_mean, transition_raw = (rows.split(batch) for rows in rest[n_transition - 1 : n_transition + 1])
        params = rest[n_transition + 1 :]
        posterior_bounds, transition_bounds = ctx.bounds
        posterior_weights, transition_weights = list(params[: 2 * n_posterior : 2]), list(params[2 * n_posterior :: 2])
        feature_dim, action_dim = rows_features.shape[1], rows_actions.shape[1]
        # The first layers' weights by input: [feature, z2_prev, action] and [z1, z2_prev, action]
        posterior_feature, posterior_z2, posterior_action = posterior_weights[0].split([feature_dim, z2_dim, action_dim], 1)
        transition_z1, transition_z2, transition_action = transition_weights[0].split([z1_dim, z2_dim, action_dim], 1)

        # Output index t + 1 is step t's; index 0 is the first frame's, an input passed through
        grads_z1_mean, grads_z1_std = grad_z1_mean.unbind(1), grad_z1_std.unbind(1)
        grads_z1, grads_z2 = grad_z1.unbind(1), grad_z2.unbind(1)
        z1_eps, z2_eps = z1_noise.unbind(0), z2_noise.unbind(0)
        # Each layer's output gradients, last step first
        posterior_grads: list[list[Tensor]] = [[] for _ in range(n_posterior)]
        transition_grads: list[list[Tensor]] = [[] for _ in range(n_transition)]
        grad_z2_now = grads_z2[-1]
        for t in range(steps - 1, -1, -1):
            # z2 = mean + std * noise, each a function of the MLP's output, then back through z2's transition
            grad_mean, grad_raw = transition_bounds.backward(
                grad_z2_now, grad_z2_now * z2_eps[t], transition_mean[t], transition_raw[t]
            )
            grad_in = _mlp_backward(
                torch.cat([grad_mean, grad_raw], dim=1),
                [layer[t] for layer in transition_hidden],
                transition_weights,
                transition_grads,
            )
            # z1 feeds z2's transition and is an output; z1_mean (through z1 too) and z1_std are outputs
            grad_z1_now = torch.addmm(grads_z1[t + 1], grad_in, transition_z1)
            grad_std = torch.addcmul(grads_z1_std[t + 1], grad_z1_now, z1_eps[t])
            grad_mean, grad_raw = posterior_bounds.backward(
                grads_z1_mean[t + 1] + grad_z1_now, grad_std, posterior_mean[t], posterior_raw[t]
            )
            grad_posterior_in = _mlp_backward(
                torch.cat([grad_mean, grad_raw], dim=1),
                [layer[t] for layer in posterior_hidden],
                posterior_weights,
                posterior_grads,
            )
            # The previous z2 feeds both MLPs of this step and is an output itself
            grad_z2_now = torch.addmm(grads_z2[t], grad_in, transition_z2).addmm_(grad_posterior_in, posterior_z2)

        # Every weight's and bias's gradient over all steps at once: layer inputs and output gradients in time-major rows
        posterior_inputs = [torch.cat([rows_features, transition_in[:, z1_dim:], rows_actions], dim=1), *posterior_rows]
        transition_inputs = [torch.cat([transition_in, rows_actions], dim=1), *transition_rows]
        param_grads: list[Tensor] = []
        first_grads = []
        for inputs, grads in ((posterior_inputs, posterior_grads), (transition_inputs, transition_grads)):
            for layer_input, layer_grads in zip(inputs, grads, strict=True):
                rows_grad = torch.cat(layer_grads[::-1])
                param_grads += [rows_grad.t().mm(layer_input), rows_grad.sum(dim=0)]
            first_grads.append(torch.cat(grads[0][::-1]))

        def per_sequence(rows: Tensor) -> Tensor:
            return rows.view(steps, batch, -1).transpose(0, 1)

        grad_features = per_sequence(first_grads[0].mm(posterior_feature))
        grad_actions = None
        if ctx.needs_input_grad[1]:
            grad_actions = per_sequence(first_grads[0].mm(posterior_action).addmm_(first_grads[1], transition_action))
        first_inputs = (grads_z1_mean[0], grads_z1_std[0], grads_z1[0], grad_z2_now)
        return grad_features, grad_actions, *first_inputs, None, None, None, None, *param_grads


def posterior_steps(
    features: Tensor,
    actions: Tensor,
    first: tuple[Tensor, Tensor, Tensor, Tensor],
    z1_noise: Tensor,
    z2_noise: Tensor,
    z1_posterior: nn.Module,
    z2_transition: nn.Module,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """
    The posterior rollout from the first frame's latent: ``z1_t ~ q(z1 | f_t, z2_{t-1}, a_{t-1})`` then
    ``z2_t ~ p(z2 | z1_t, z2_{t-1}, a_{t-1})``, reparameterised with the given noise; one autograd node when a gradient
    is needed.

    :param features: (B, T, F) encoder features of frames 1..T
    :param actions: (B, T, A) actions 0..T-1
    :param first: frame 0's z1 posterior mean and std, z1 and z2: (B, Z1) three times, (B, Z2)
    :param z1_noise: (T, B, Z1) standard normal noise of the z1 samples of frames 1..T
    :param z2_noise: (T, B, Z2) standard normal noise of the z2 samples of frames 1..T
    :param z1_posterior: the ``GaussianMLP`` of z1's posterior (its ``bounds`` make its mean and std)
    :param z2_transition: the ``GaussianMLP`` of z2's transition
    :return: z1's posterior mean and std, z1 and z2 of frames 0..T, each (B, T+1, dim)
    """
    posterior_params = [param for layer in linear_layers(z1_posterior) for param in (layer.weight, layer.bias)]
    transition_params = [param for layer in linear_layers(z2_transition) for param in (layer.weight, layer.bias)]
    bounds = (z1_posterior.bounds, z2_transition.bounds)
    if not torch.is_grad_enabled():
        outputs, _ = _rollout(
            features, actions, first, z1_noise, z2_noise, posterior_params, transition_params, bounds, keep=False
        )
        return outputs
    return _PosteriorSteps.apply(
        features, actions, *first, z1_noise, z2_noise, len(posterior_params), bounds, *posterior_params, *transition_params
    )
