"""
The networks: the latent model, actor and critics, and the torch pieces they are built of (convolutions, Gaussians,
optimizer steps, numerics). Torch and NumPy only: nothing here imports Stable-Baselines3 or another folder of the
package.
"""
