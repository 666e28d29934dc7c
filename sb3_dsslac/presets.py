"""Named hyperparameter sets of the command line: ``thesis`` (Table 5.2) and ``cpu`` (a few minutes on a laptop CPU)."""

from typing import Any

PRESETS: dict[str, dict[str, Any]] = {
    # DSSLAC's defaults are the thesis's Table 5.2
    "thesis": {},
    # Small networks, a short warm-up and few updates: runs end to end in minutes on a 2-core CPU, learns little
    "cpu": {
        "buffer_size": 20_000,
        "learning_starts": 1_000,
        "latent_pretrain_steps": 50,
        "batch_size": 16,
        "latent_batch_size": 8,
        "sequence_length": 4,
        "train_freq": 100,
        "gradient_steps": 4,
        "n_quantiles": 16,
        "policy_kwargs": {
            "z1_dim": 16,
            "z2_dim": 64,
            "feature_dim": 64,
            "hidden_units": [64, 64],
            "n_cosines": 16,
            "cost_critic_hidden_dim": 64,
        },
    },
}


def preset_hyperparams(name: str, overrides: dict[str, Any] | None = None) -> dict[str, Any]:
    """
    The keywords of ``DSSLAC`` of preset ``name`` with ``overrides`` on top (``policy_kwargs`` merged key by key).

    :param name: a key of ``PRESETS``
    :param overrides: DSSLAC keywords that replace the preset's
    :return: a new dict of DSSLAC keywords
    """
    if name not in PRESETS:
        raise ValueError(f"Unknown preset {name!r}; valid presets: {sorted(PRESETS)}")
    hyperparams = {key: (dict(value) if isinstance(value, dict) else value) for key, value in PRESETS[name].items()}
    for key, value in (overrides or {}).items():
        if key == "policy_kwargs" and isinstance(value, dict):
            hyperparams["policy_kwargs"] = {**hyperparams.get("policy_kwargs", {}), **value}
        else:
            hyperparams[key] = value
    return hyperparams
