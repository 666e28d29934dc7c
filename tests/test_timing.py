"""The time account: activities nest without double counting, and the rest of the wall time is ``other``."""

import pickle
import time

import pytest

from sb3_dsslac.common.timing import ACTIVITIES, TimeAccount, measured


def test_nested_activities_are_counted_once() -> None:
    account = TimeAccount()
    with account.running():
        with account.measure("acting"):
            time.sleep(0.05)
            with account.measure("evaluation"):
                time.sleep(0.1)
            time.sleep(0.05)
        time.sleep(0.05)
    summary = account.summary()
    assert summary["evaluation"] == pytest.approx(0.1, abs=0.03)
    assert summary["acting"] == pytest.approx(0.1, abs=0.03)
    assert summary["other"] == pytest.approx(0.05, abs=0.03)
    assert summary["wall"] == pytest.approx(sum(summary[name] for name in (*ACTIVITIES, "other")), rel=1e-6)
    assert summary["cpu"] < summary["wall"]  # it slept


def test_running_activity_is_counted_up_to_now_and_once() -> None:
    account = TimeAccount()
    with account.running(), account.measure("updates"):
        time.sleep(0.05)
        midway = account.summary()["updates"]
        time.sleep(0.05)
    assert midway == pytest.approx(0.05, abs=0.03)
    assert account.summary()["updates"] == pytest.approx(0.1, abs=0.03)


def test_account_survives_pickling_and_keeps_adding() -> None:
    account = TimeAccount()
    with account.running(), account.measure("checkpoints"):
        time.sleep(0.02)
        restored = pickle.loads(pickle.dumps(account))  # saved mid-activity, as a checkpoint is
    with restored.running(), restored.measure("checkpoints"):
        time.sleep(0.02)
    assert restored.summary()["checkpoints"] >= 0.035
    assert restored.summary()["wall"] >= 0.035


def test_unknown_activity_and_models_without_account() -> None:
    with pytest.raises(ValueError, match="Unknown activity 'naps'"):
        with TimeAccount().measure("naps"):
            pass
    with measured(object(), "evaluation"):  # another algorithm: nothing is measured, nothing fails
        pass
