"""Pins of the behaviour behind the thesis numbers: defaults, step-size milestone, TD targets, losses and isolation."""

import pytest

from sb3_dsslac import DSSLAC, lagrange
from sb3_dsslac.presets import PRESETS, THESIS_LR_DECAY_MILESTONE
from tests.synthetic_envs import HazardPointEnv
from tests.test_dsslac import SMALL, small_model

OPTIMIZERS = ("latent_optimizer", "actor_optimizer", "critic_optimizer", "cost_critic_optimizer")


def step_sizes(model: DSSLAC) -> dict[str, float]:
    """Every optimizer's step size and the multiplier's."""
    sizes = {name: getattr(model.policy, name).param_groups[0]["lr"] for name in OPTIMIZERS}
    assert model.ent_coef_optimizer is not None
    sizes["ent_coef_optimizer"] = model.ent_coef_optimizer.param_groups[0]["lr"]
    sizes["lagrange"] = model.current_lagrange_learning_rate
    return sizes


# ----------------------------------------------------------------------------------------------------------------------
# Step-size milestone
# ----------------------------------------------------------------------------------------------------------------------


def test_thesis_milestone_is_the_reference_codes() -> None:
    # MultiStepLR(milestones=[400]) stepped every 1000 simulator steps after the 60k-simulator-step warm-up
    assert THESIS_LR_DECAY_MILESTONE * 2 == 60_000 + 400 * 1000
    for name in ("thesis", "thesis_fast"):
        assert PRESETS[name]["lr_decay_milestone"] == 230_000
    assert "lr_decay_milestone" not in PRESETS["cpu"]


def test_milestone_halves_every_step_size_once() -> None:
    model = small_model(HazardPointEnv(), lr_decay_milestone=100, learning_rate=3e-4, latent_learning_rate=2e-4)
    model.learn(45)
    model.num_timesteps = 99
    model.train(gradient_steps=1, batch_size=8)
    before = step_sizes(model)
    assert before == {
        "latent_optimizer": 2e-4,
        "actor_optimizer": 3e-4,
        "critic_optimizer": 3e-4,
        "cost_critic_optimizer": 3e-4,
        "ent_coef_optimizer": 3e-4,
        "lagrange": 2e-4,
    }
    model.num_timesteps = 100
    for _ in range(2):  # the factor applies once, not once per train() call
        model.train(gradient_steps=1, batch_size=8)
        assert step_sizes(model) == {name: pytest.approx(0.5 * value) for name, value in before.items()}


def test_no_milestone_no_decay() -> None:
    model = small_model(HazardPointEnv())
    model.learn(45)
    model.num_timesteps = 10**9
    model.train(gradient_steps=1, batch_size=8)
    assert step_sizes(model)["actor_optimizer"] == 2e-4 and step_sizes(model)["latent_optimizer"] == 1e-4


@pytest.mark.parametrize("rule", ["sgd", "episode", "critic"])
def test_multiplier_steps_with_the_decayed_step_size(rule: str, monkeypatch) -> None:
    rates = []
    original = lagrange.sgd_lagrange_step

    def spy(raw: float, cost: float, budget: float, learning_rate: float) -> float:
        rates.append(learning_rate)
        return original(raw, cost, budget, learning_rate)

    monkeypatch.setattr("sb3_dsslac.lagrange.sgd_lagrange_step", spy)
    monkeypatch.setattr("sb3_dsslac.dsslac.sgd_lagrange_step", spy)
    model = small_model(HazardPointEnv(), lagrange=rule, lr_decay_milestone=50, lr_decay_factor=0.25)
    model.learn(80)
    assert rates and set(rates) <= {2e-4, 0.25 * 2e-4}
    assert rates[-1] == pytest.approx(0.25 * 2e-4)


def test_milestone_is_saved_and_a_resumed_run_keeps_the_decayed_step_sizes(tmp_path) -> None:
    model = small_model(HazardPointEnv(), lr_decay_milestone=60, lr_decay_factor=0.1)
    model.learn(50)
    assert step_sizes(model)["actor_optimizer"] == pytest.approx(2e-4)
    model.save(tmp_path / "model.zip")
    loaded = DSSLAC.load(tmp_path / "model.zip", env=HazardPointEnv())
    assert (loaded.lr_decay_milestone, loaded.lr_decay_factor) == (60, 0.1)
    loaded.learn(30, reset_num_timesteps=False)
    assert loaded.num_timesteps == 80
    assert step_sizes(loaded) == pytest.approx({name: 0.1 * value for name, value in step_sizes(model).items()})
    loaded.save(tmp_path / "resumed.zip")
    again = DSSLAC.load(tmp_path / "resumed.zip", env=HazardPointEnv())
    again.learn(10, reset_num_timesteps=False)
    assert step_sizes(again) == pytest.approx(step_sizes(loaded))


def test_bad_milestone_keywords_are_rejected() -> None:
    with pytest.raises(ValueError, match="lr_decay_factor"):
        small_model(HazardPointEnv(), lr_decay_factor=0.0)
    with pytest.raises(ValueError, match="lr_decay_milestone"):
        small_model(HazardPointEnv(), lr_decay_milestone=-1)


# ----------------------------------------------------------------------------------------------------------------------
# Keywords given twice
# ----------------------------------------------------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("name", "value", "other"),
    [
        ("image_noise", 0.1, 0.2),
        ("cost_loss_weight", 3.0, 4.0),
        ("cost_positive_weight", 10.0, 20.0),
        ("latent_learning_rate", 1e-3, 2e-3),
        ("cost_critic", "mean", "iqn"),
    ],
)
def test_a_keyword_given_twice_must_agree(name: str, value, other) -> None:
    policy_kwargs = {**SMALL["policy_kwargs"], name: other}
    with pytest.raises(ValueError, match=rf"{name}={value!r} and policy_kwargs=.*{other!r}"):
        small_model(HazardPointEnv(), policy_kwargs=policy_kwargs, **{name: value})
    agreeing = small_model(HazardPointEnv(), policy_kwargs={**SMALL["policy_kwargs"], name: value}, **{name: value})
    assert agreeing.policy_kwargs[name] == value


def test_policy_kwargs_alone_are_used_and_not_modified(tmp_path) -> None:
    policy_kwargs = {**SMALL["policy_kwargs"], "image_noise": 0.05, "latent_learning_rate": 3e-4, "cost_critic": "mean"}
    given = dict(policy_kwargs)
    model = small_model(HazardPointEnv(), policy_kwargs=policy_kwargs)
    assert policy_kwargs == given
    assert model.policy.latent.image_std == pytest.approx(0.05**0.5)
    assert model.latent_learning_rate == 3e-4 and model.policy.latent_optimizer.param_groups[0]["lr"] == 3e-4
    assert model.cost_critic == "mean" and type(model.policy.cost_critic).__name__ == "MeanCostCritic"
    default = small_model(HazardPointEnv())
    assert default.policy.latent.image_std == pytest.approx(0.4**0.5) and default.cost_critic == "iqn"

    model = small_model(HazardPointEnv(), image_noise=0.07, cost_loss_weight=5.0)
    model.learn(45)
    model.save(tmp_path / "model.zip")
    loaded = DSSLAC.load(tmp_path / "model.zip", env=HazardPointEnv())
    assert loaded.policy.latent.image_std == pytest.approx(0.07**0.5)
    assert loaded.policy.latent.cost_loss_weight == 5.0
    loaded.learn(10, reset_num_timesteps=False)
