"""
How large are a run's latents? The latent model's loss does not fix their scale (the KL between the posterior and the
learned prior is the same if both grow together; only the first frame's prior is a fixed N(0, I)), and the larger they
are, the more one burst of optimizer steps changes the networks that read them. On replayed windows of a run's newest
checkpoint this prints, per dimension of z1, the KL per step, the posterior's and the prior's std and the posterior
mean's size; then |z1| and |z2| quantiles, z2's std, and how much z2's recurrence stretches (the spectral norm of the
Jacobian of z2's transition mean with respect to the previous z2).

    python benchmarks/tools/diagnostics/latent_scale.py runs/<run>  # a run of `python -m sb3_dsslac train` with a checkpoint
    python benchmarks/tools/diagnostics/latent_scale.py runs/<run> --windows 512
"""

import argparse
import sys
from pathlib import Path

# The benchmarks' shared modules (machine.py) sit one folder up
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import torch as th
from machine import cpu_model
from run_checkpoint import checkpoint_model

from sb3_dsslac.nn.latent import LatentModel, gaussian_kl


def quantiles(values: th.Tensor) -> str:
    """Median, 99th percentile and largest of |values|."""
    size = values.abs().flatten()
    return f"median {size.median():8.3f}  p99 {size.quantile(0.99):8.3f}  max {size.max():9.3f}"


def recurrence_stretch(latent: LatentModel, z1: th.Tensor, z2: th.Tensor, action: th.Tensor) -> th.Tensor:
    """The spectral norm of d mean(z2' | z1, z2, a) / d z2 at one step: above 1, the step stretches z2."""
    jacobian = th.autograd.functional.jacobian(lambda previous: latent.z2_transition(z1, previous, action)[0], z2)
    return th.linalg.matrix_norm(jacobian, ord=2)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("run", type=Path, help="a run folder with a checkpoint (model and replay buffer)")
    parser.add_argument("--windows", type=int, default=256, help="replayed windows")
    parser.add_argument("--jacobians", type=int, default=16, help="windows whose z2 recurrence Jacobian is measured")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args()
    model, checkpoint = checkpoint_model(args.run)
    latent = model.policy.latent
    print(f"{checkpoint.model} ({checkpoint.timesteps} agent steps), {cpu_model()}")

    th.manual_seed(args.seed)
    batch = model.replay_buffer.sample(args.windows)
    with th.no_grad():
        features = latent.encode(model.policy.preprocess(batch.observations))
        rollout = latent.posterior(features, batch.actions)
        prior_mean, prior_std = latent.z1_prior(rollout.z2[:, :-1], batch.actions)
        _, z2_std = latent.z2_transition(rollout.z1[:, 1:], rollout.z2[:, :-1], batch.actions)
        kl = gaussian_kl(rollout.z1_mean[:, 1:], rollout.z1_std[:, 1:], prior_mean, prior_std)  # (B, T, Z1)

    print("\nz1 dim | KL per step | posterior std | prior std | posterior mean (rms)")
    for dim in range(latent.z1_dim):
        posterior_std, std = rollout.z1_std[:, 1:, dim].mean(), prior_std[..., dim].mean()
        size = rollout.z1_mean[:, 1:, dim].square().mean().sqrt()
        print(f"{dim:6d} | {kl[..., dim].mean():11.3f} | {posterior_std:13.3f} | {std:9.3f} | {size:8.3f}")
    print()
    for name, values in (
        ("z1 posterior mean", rollout.z1_mean),
        ("z1 posterior std", rollout.z1_std),
        ("z1 prior mean", prior_mean),
        ("z1 prior std", prior_std),
        ("z1", rollout.z1),
        ("z2", rollout.z2),
        ("z2 std", z2_std),
    ):
        print(f"{name:18s} {quantiles(values)}")

    windows = range(min(args.jacobians, args.windows))
    stretch = th.stack([recurrence_stretch(latent, rollout.z1[w, 1], rollout.z2[w, 0], batch.actions[w, 0]) for w in windows])
    print(f"z2 recurrence stretch (Jacobian spectral norm): median {stretch.median():.3f}, max {stretch.max():.3f}")


if __name__ == "__main__":
    main()
