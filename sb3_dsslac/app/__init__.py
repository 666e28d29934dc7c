"""
What a user runs on top of the algorithm: the command line and its run folders, Optuna tuning, the rl-zoo3 bridge,
plots, evaluation rollouts and belief pictures. Imports anything below; only the entry points (``python -m sb3_dsslac``,
``python -m sb3_dsslac.zoo``) import it.
"""
