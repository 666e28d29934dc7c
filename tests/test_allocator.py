"""allocator.py: glibc's malloc keeps the updates' freed memory for reuse."""

from sb3_dsslac import dsslac
from sb3_dsslac.engine import allocator
from tests.synthetic_envs import HazardPointEnv
from tests.test_dsslac import small_model


def test_a_cpu_model_keeps_freed_memory(monkeypatch) -> None:
    calls = []
    monkeypatch.setattr(dsslac, "keep_freed_memory", lambda: calls.append(True) or True)
    small_model(HazardPointEnv())
    assert calls == [True]


def test_keep_freed_memory_sets_both_thresholds(monkeypatch) -> None:
    calls = []
    monkeypatch.setattr(allocator, "_mallopt", lambda: lambda option, value: calls.append((option, value)) or 1)
    assert allocator.keep_freed_memory()
    assert calls == [(allocator.M_MMAP_THRESHOLD, 32 * 2**20), (allocator.M_TRIM_THRESHOLD, 2**30)]


def test_keep_freed_memory_reports_a_c_library_without_mallopt(monkeypatch) -> None:
    monkeypatch.setattr(allocator, "_mallopt", lambda: None)
    assert not allocator.keep_freed_memory()
    monkeypatch.setattr(allocator, "_mallopt", lambda: lambda option, value: 0)  # refused
    assert not allocator.keep_freed_memory()
