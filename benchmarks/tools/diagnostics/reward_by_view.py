"""
Where the reward is earned: a trained agent's reward per agent step, and the scripted controller's of
``benchmarks/ceiling.py`` beside it, split by what the frame acted on shows of the goal (at least 1, 3 and 10 goal
pixels, and ``goal_view``'s in-view rule: 10/4096 of the frame) and by whether the goal's centre was inside the camera's
horizontal field of view (from the simulator state). The same env settings (the run's) and reset seeds for all.

    python benchmarks/tools/diagnostics/reward_by_view.py runs/<run>                  # its model.zip (or newest checkpoint)
    python benchmarks/tools/diagnostics/reward_by_view.py runs/<run>/model.zip --episodes 10
    python benchmarks/tools/diagnostics/reward_by_view.py --env SafetyGym/PointGoal1-v0 --size 32   # the script alone
    python benchmarks/tools/diagnostics/reward_by_view.py runs/<run> --search-after 1 4   # + the agent with a search
    python benchmarks/tools/diagnostics/reward_by_view.py runs/<run> --keep-turn-after 3  # + its turns kept one way

``--search-after N``: the trained agent again, its actions replaced by the script's search (turn left in place) once
the goal has been out of view for N frames in a row, until it shows again; its filter is told the action taken. What
the agent would earn if it looked for the goal as the script does, at its own skill while the goal is in view.
``--keep-turn-after N`` (a Point): the agent's own actions, but once the goal has been out of view for N frames its
turn keeps the direction of its first turn past that point, at the agent's own turn rate and forward force: what a
policy that holds a turn's direction, and nothing else, would earn.

"Otherwise": the reward per step on the other steps. "Share of the reward": the part of the episodes' total reward
earned on the condition's steps (above 100% where the other steps lose reward; n/a where the total is not positive).
"""

import argparse
import sys
from collections.abc import Callable
from pathlib import Path

# The benchmarks' shared modules (ceiling.py, goal_view.py, machine.py) sit one folder up
sys.path.insert(0, str(Path(__file__).resolve().parents[2]))

import numpy as np
import torch as th
from ceiling import ACTION_REPEAT, CONTROLLERS, Episode, controller_for, run_episode
from goal_view import goal_mask, in_view, min_pixels
from machine import cpu_model

from sb3_dsslac import DSSLAC
from sb3_dsslac.app.runs import FINAL_MODEL, find_checkpoint, find_run_config, load_config
from sb3_dsslac.common.envs import make_env

PIXEL_COUNTS = (1, 3, 10)


def require_point(env, env_id: str, what: str) -> None:
    """Exit with a message unless ``env``'s robot is the Point, whose actions (forward force, turn rate) ``what`` uses."""
    robot = env.unwrapped.robot_spec.name
    if robot != "Point":
        raise SystemExit(f"{what}: the Point's actions (forward, turn), not the {robot}'s ({env_id})")


class ModelAgent:
    """A DS-SLAC agent acting on frames one at a time, its latent filter carried between them (``reset`` at a new episode)."""

    def __init__(self, model: DSSLAC, deterministic: bool = False) -> None:
        self.model, self.deterministic = model, deterministic
        self.state: tuple[np.ndarray, np.ndarray] | None = None

    def reset(self) -> None:
        self.state = None

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        action, self.state = self.model.predict(frame, self.state, np.zeros(1, dtype=bool), self.deterministic)
        return action


class OutOfViewAgent(ModelAgent):
    """
    ``ModelAgent`` whose action ``replace`` changes once the goal has been out of view for ``after`` frames in a row,
    until it shows again; the filter's last action is the one taken.
    """

    def __init__(self, model: DSSLAC, after: int, deterministic: bool = False) -> None:
        super().__init__(model, deterministic)
        self.after, self.out_of_view = after, 0

    def reset(self) -> None:
        super().reset()
        self.out_of_view = 0

    def replace(self, frame: np.ndarray, action: np.ndarray, first: bool) -> np.ndarray:
        """The action taken instead of the agent's ``action`` (first: the first replaced step since the goal left)."""
        raise NotImplementedError

    def __call__(self, frame: np.ndarray) -> np.ndarray:
        action = super().__call__(frame)
        self.out_of_view = 0 if in_view(goal_mask(frame)) else self.out_of_view + 1
        if self.out_of_view < self.after:
            return action
        assert self.state is not None
        action = self.replace(frame, action, first=self.out_of_view == self.after)
        self.state = (self.state[0], self.model.policy.scale_action(action)[None])
        return action


class SearchingAgent(OutOfViewAgent):
    """``OutOfViewAgent`` that searches as ``search`` does (the script's turn in place)."""

    def __init__(self, model: DSSLAC, search: Callable[[np.ndarray], np.ndarray], after: int, deterministic: bool = False):
        super().__init__(model, after, deterministic)
        self.search = search

    def replace(self, frame: np.ndarray, action: np.ndarray, first: bool) -> np.ndarray:
        return self.search(frame)


class TurnKeepingAgent(OutOfViewAgent):
    """
    ``OutOfViewAgent`` of a Point (actions: forward force, turn rate) that keeps its own forward force and turn rate's
    magnitude but turns the way it turned at its first replaced step, until the goal shows again: the agent's own
    behaviour with a turn kept in one direction.
    """

    def __init__(self, model: DSSLAC, after: int, deterministic: bool = False) -> None:
        super().__init__(model, after, deterministic)
        self.direction = 1.0

    def replace(self, frame: np.ndarray, action: np.ndarray, first: bool) -> np.ndarray:
        if first:
            self.direction = 1.0 if action[1] >= 0.0 else -1.0
        return np.array([action[0], self.direction * abs(action[1])], dtype=action.dtype)


def conditions(episode: Episode, size: tuple[int, int]) -> dict[str, np.ndarray]:
    """(T,) bool per condition on an episode's steps; ``size``: (height, width) of its frames."""
    shown = {f"goal pixels >= {count}": episode.goal_pixels >= count for count in PIXEL_COUNTS}
    shown["goal in view (goal_view's rule)"] = episode.goal_pixels >= min_pixels(*size)
    shown["goal in the field of view"] = episode.in_fov
    shown["in the field of view, no goal pixel"] = episode.in_fov & (episode.goal_pixels == 0)
    return shown


def reward_split(episodes: list[Episode], size: tuple[int, int]) -> dict[str, dict[str, float | None]]:
    """
    Per condition: the share of steps it holds, the mean reward per step on them and on the others, and the share of
    the total reward earned on them (None where undefined).
    """
    reward = np.concatenate([episode.rewards for episode in episodes])
    total = float(reward.sum())
    names = conditions(episodes[0], size).keys()
    split = {}
    for name in names:
        held = np.concatenate([conditions(episode, size)[name] for episode in episodes])
        split[name] = {
            "share of steps": float(held.mean()),
            "reward per step": float(reward[held].mean()) if held.any() else None,
            "otherwise": float(reward[~held].mean()) if (~held).any() else None,
            "share of the reward": float(reward[held].sum()) / total if total > 0 else None,
        }
    return split


def split_rows(agent: str, episodes: list[Episode], size: tuple[int, int]) -> list[str]:
    """Markdown rows of ``reward_split``, the agent's mean episode reward and cost in the first."""
    mean_reward = np.mean([episode.rewards.sum() for episode in episodes])
    mean_cost = np.mean([episode.costs.sum() for episode in episodes])

    def cell(value: float | None, form: str) -> str:
        return "n/a" if value is None else format(value, form)

    rows = []
    for k, (name, values) in enumerate(reward_split(episodes, size).items()):
        first = f"{agent} | {mean_reward:.2f} / {mean_cost:.1f}" if k == 0 else " | "
        rows.append(
            f"| {first} | {name} | {values['share of steps']:.1%} | {cell(values['reward per step'], '.3f')} | "
            f"{cell(values['otherwise'], '.3f')} | {cell(values['share of the reward'], '.0%')} |"
        )
    return rows


TABLE_HEADER = (
    "| agent | reward / cost per episode | steps where | share of steps | reward per step | otherwise | share of the reward |"
    "\n|---|---:|---|---:|---:|---:|---:|"
)


def load_agent(path: Path) -> tuple[DSSLAC, str, dict]:
    """A run folder's final model (else its newest checkpoint) or a model file, with its run's env id and keywords."""
    if path.is_dir():
        checkpoint = find_checkpoint(path)
        model_path = path / FINAL_MODEL if (path / FINAL_MODEL).is_file() else checkpoint.model if checkpoint else None
        if model_path is None:
            raise SystemExit(f"{path} has no {FINAL_MODEL} and no checkpoint")
        config = load_config(path)
    else:
        model_path, config = path, find_run_config(path)
        if config is None:
            raise SystemExit(f"{path} is not in a run folder (no config.yaml beside it or one folder up): give the run")
    model = DSSLAC.load(model_path, device="cpu")
    if len(model.policy.latent.observation_shape) != 3:
        raise SystemExit(f"{path} is not a pixel agent: its observations are {model.policy.latent.observation_shape}")
    return model, config.env, config.env_kwargs


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    parser.add_argument("model", type=Path, nargs="?", help="a train run folder or a model.zip inside one")
    parser.add_argument("--env", default="SafetyGym/PointGoal1-v0", help="without a model: the task of the script")
    parser.add_argument("--size", type=int, default=32, help="without a model: frame width and height, pixels")
    parser.add_argument("--episodes", type=int, default=5)
    parser.add_argument("--episode-seed", type=int, default=10_000, help="reset seed of the first episode (+1 each)")
    parser.add_argument("--deterministic", action="store_true", help="the agent's mean action and filter means")
    parser.add_argument(
        "--search-after",
        type=int,
        nargs="*",
        default=[],
        metavar="N",
        help="with a model: also the agent searching as the script once the goal is out of view N frames",
    )
    parser.add_argument(
        "--keep-turn-after",
        type=int,
        nargs="*",
        default=[],
        metavar="N",
        help="with a Point model: also the agent turning one way (its own forward and turn magnitude) once the goal is "
        "out of view N frames",
    )
    args = parser.parse_args()
    if args.episodes < 1:
        parser.error("--episodes must be positive")
    for flag, counts in (("--search-after", args.search_after), ("--keep-turn-after", args.keep_turn_after)):
        if any(after < 1 for after in counts) or (counts and args.model is None):
            parser.error(f"{flag} takes positive frame counts and a model")
    agents: dict[str, Callable[[np.ndarray], np.ndarray]] = {}
    if args.model is not None:
        th.set_num_threads(1)
        model, env_id, env_kwargs = load_agent(args.model)
        agents[f"trained ({'/'.join(args.model.parts[-2:])})"] = ModelAgent(model, args.deterministic)
    else:
        env_id, env_kwargs = args.env, {"width": args.size, "height": args.size, "action_repeat": ACTION_REPEAT}
    env = make_env(env_id, "pixels", env_kwargs=env_kwargs)
    if args.keep_turn_after:
        require_point(env, env_id, "--keep-turn-after")
    seeds = range(args.episode_seed, args.episode_seed + args.episodes)
    try:
        env.reset(seed=seeds[0])
        scripts = {name: controller_for(env, name) for name in CONTROLLERS}
        for after in args.search_after:
            agents[f"trained, the script's search after {after} frames out of view"] = SearchingAgent(
                model, scripts["seek"], after, args.deterministic
            )
        for after in args.keep_turn_after:
            agents[f"trained, its turn kept one way after {after} frames out of view"] = TurnKeepingAgent(
                model, after, args.deterministic
            )
        agents.update({f"script ({name})": script for name, script in scripts.items()})
        size = env.observation_space.shape[:2]
        print(f"{env_id} {env_kwargs}, {args.episodes} episodes (reset seeds from {args.episode_seed}); {cpu_model()}\n")
        print(TABLE_HEADER)
        for name, agent in agents.items():
            episodes = [run_episode(env, agent, seed) for seed in seeds]
            print("\n".join(split_rows(name, episodes, size)), flush=True)
    finally:
        env.close()


if __name__ == "__main__":
    main()
