"""What a run trains, the fields that a training run (``TrainConfig``) and each trial of a study (``TuneSpec``) share."""

from dataclasses import dataclass, field
from typing import Any

from sb3_dsslac.presets import PRESETS, preset_env_kwargs


@dataclass
class Experiment:
    """
    The task, its observations and env keywords, the hyperparameters and where they run. Steps are simulator steps.

    :param env: env id (see ``make_env``)
    :param sim_steps: simulator steps of training
    :param preset: a name of ``sb3_dsslac.presets.PRESETS``
    :param hyperparams: DSSLAC keywords on top of the preset
    :param obs_type: "pixels" or "state" (None: the env's default)
    :param env_kwargs: other keywords of the env (``width=32, height=32``), on top of the preset's own
        (``PRESET_ENV_KWARGS``); kept merged, so a saved run names every keyword it used
    :param eval_episodes: episodes per evaluation
    :param device: "auto", "cpu" or "cuda"
    :param threads: torch CPU threads (None: torch's default; 1 is often fastest for small networks on a busy CPU)
    """

    env: str
    sim_steps: int = 1_000_000
    preset: str = "thesis"
    hyperparams: dict[str, Any] = field(default_factory=dict)
    obs_type: str | None = None
    env_kwargs: dict[str, Any] = field(default_factory=dict)
    eval_episodes: int = 10
    device: str = "auto"
    threads: int | None = None

    def __post_init__(self) -> None:
        if self.preset not in PRESETS:
            raise ValueError(f"Unknown preset {self.preset!r}; valid presets: {sorted(PRESETS)}")
        if not isinstance(self.env_kwargs, dict):
            raise ValueError(f"env_kwargs must be a mapping of env keywords, got {self.env_kwargs!r}")
        self.env_kwargs = preset_env_kwargs(self.preset, self.env_kwargs)
        for name in ("sim_steps", "eval_episodes"):
            if getattr(self, name) < 1:
                raise ValueError(f"{name} must be positive, got {getattr(self, name)}")
        if self.threads is not None and self.threads < 1:
            raise ValueError(f"threads must be positive or None, got {self.threads}")
