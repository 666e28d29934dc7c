"""A preset named after a measured configuration is that configuration: its keywords are the recorded run's."""

import json
from pathlib import Path

import pytest
import yaml

from sb3_dsslac.presets import preset_env_kwargs, preset_hyperparams

RESULTS = Path(__file__).parent.parent / "benchmarks" / "results"

# preset -> the committed run (its seed's config.yaml) whose resolved DSSLAC keywords and env keywords it names
MEASURED_AS = {
    "cpu_pixels32_pid": "learning_PointGoal1_pixels_cpu_pixels32_bounded_actor_critic_transitions_4_n_quantiles_8_lagrange_pid"
    "_pid_kp_0.004_pid_ki_0.0001_pid_kd_0/seed20_run/config.yaml",
    "cpu_pixels32_prev_action": "learning_PointGoal1_pixels_cpu_pixels32_prev_action/seed20_run/config.yaml",
    "cpu_pixels32_gru_overshooting": "learning_PointGoal1_pixels_cpu_pixels32_gru_overshooting/seed60_run/config.yaml",
}


@pytest.mark.parametrize("preset", sorted(MEASURED_AS))
def test_the_preset_is_the_measured_run(preset: str) -> None:
    config = yaml.safe_load((RESULTS / MEASURED_AS[preset]).read_text())
    recorded = dict(config["resolved"]["dsslac"])
    recorded.pop("episode_length")  # read from the env's time limit, not a preset's
    assert json.loads(json.dumps(preset_hyperparams(preset))) == recorded  # tuples as the record's lists
    assert preset_env_kwargs(preset) == config["env_kwargs"]
