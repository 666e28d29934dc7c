"""Where a run's time goes: wall seconds by activity (acting, updates, evaluations, ...) and the process's CPU seconds."""

import contextlib
import resource
import time
from collections.abc import Iterator
from typing import Any

# The activities of a training run, in the order they are reported
ACTIVITIES = ("acting", "updates", "latent_pretraining", "compilation", "evaluation", "checkpoints", "logging")


def process_cpu_seconds() -> float:
    """User + system CPU seconds of this process so far (all its threads)."""
    usage = resource.getrusage(resource.RUSAGE_SELF)
    return usage.ru_utime + usage.ru_stime


class TimeAccount:
    """
    Wall seconds spent in each of ``ACTIVITIES`` while ``running``. Activities nest without being counted twice: while
    an inner one runs (an evaluation inside acting, the compilation inside updates), the outer one's clock stops.
    Whatever ran outside every activity is ``other``. Saved with the model, so a resumed run keeps its account.
    """

    def __init__(self) -> None:
        self.seconds = dict.fromkeys(ACTIVITIES, 0.0)
        self.wall_seconds = 0.0
        self.cpu_seconds = 0.0
        self._stack: list[list[Any]] = []  # [activity, start of its current stretch]
        self._running_since: tuple[float, float] | None = None  # wall and CPU clocks when `running` began

    def __getstate__(self) -> dict[str, Any]:
        """The totals up to now (a checkpoint saved mid-activity keeps the time so far); no clocks of this process."""
        summary = self.summary()
        state = self.__dict__.copy()
        state["seconds"] = {name: summary[name] for name in ACTIVITIES}
        state["wall_seconds"], state["cpu_seconds"] = summary["wall"], summary["cpu"]
        state["_stack"], state["_running_since"] = [], None
        return state

    @contextlib.contextmanager
    def running(self) -> Iterator[None]:
        """Count the wall and CPU time of the block (a ``learn`` call) into the totals; re-entrant."""
        if self._running_since is not None:
            yield
            return
        self._running_since = (time.perf_counter(), process_cpu_seconds())
        try:
            yield
        finally:
            self._add_running()
            self._running_since = None

    def _add_running(self) -> None:
        if self._running_since is not None:
            wall, cpu = time.perf_counter(), process_cpu_seconds()
            self.wall_seconds += wall - self._running_since[0]
            self.cpu_seconds += cpu - self._running_since[1]
            self._running_since = (wall, cpu)

    @contextlib.contextmanager
    def measure(self, activity: str) -> Iterator[None]:
        """Count the block's wall seconds as ``activity`` (minus those of activities measured inside it)."""
        if activity not in self.seconds:
            raise ValueError(f"Unknown activity {activity!r}; activities: {', '.join(ACTIVITIES)}")
        now = time.perf_counter()
        if self._stack:
            outer = self._stack[-1]
            self.seconds[outer[0]] += now - outer[1]
        self._stack.append([activity, now])
        try:
            yield
        finally:
            now = time.perf_counter()
            self.seconds[activity] += now - self._stack.pop()[1]
            if self._stack:
                self._stack[-1][1] = now

    def summary(self) -> dict[str, float]:
        """
        Seconds by activity, ``other`` (the rest of the wall time), ``wall`` and the process's ``cpu`` seconds, up to
        now (the innermost activity still running counted up to now; the ones around it are paused).
        """
        self._add_running()
        seconds = dict(self.seconds)
        if self._stack:
            activity, start = self._stack[-1]
            seconds[activity] += time.perf_counter() - start
        measured = sum(seconds.values())
        return {**seconds, "other": max(self.wall_seconds - measured, 0.0), "wall": self.wall_seconds, "cpu": self.cpu_seconds}

    def format(self) -> str:
        """One line: minutes and share of the wall time of each activity that took any time."""
        summary = self.summary()
        wall = max(summary["wall"], 1e-9)
        parts = [
            f"{name.replace('_', ' ')} {summary[name] / 60:.1f} min ({summary[name] / wall:.0%})"
            for name in (*ACTIVITIES, "other")
            if summary[name] > 0.0
        ]
        return f"{summary['wall'] / 60:.1f} wall minutes ({summary['cpu'] / 60:.1f} CPU): " + ", ".join(parts)


def measured(model: Any, activity: str) -> contextlib.AbstractContextManager:
    """``model.time_account.measure(activity)`` where the model keeps an account (DSSLAC does), else nothing."""
    account = getattr(model, "time_account", None)
    return account.measure(activity) if isinstance(account, TimeAccount) else contextlib.nullcontext()
