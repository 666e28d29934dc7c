"""
The Stable-Baselines3 pieces DS-SLAC is made of: the policy, the sequence replay buffer, the Lagrange multiplier, the
cost evaluation, env helpers, input checks and time accounting. Imports ``sb3_dsslac.nn`` and nothing above it.
"""
