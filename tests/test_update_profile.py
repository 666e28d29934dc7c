"""benchmarks/update_profile.py: the by-part table of one DS-SLAC update at the smallest pixel shapes."""

import math
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_update_profile_lists_every_part_with_its_flops_and_times(monkeypatch, capsys) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))
    import update_profile

    update_profile.main(["--preset", "cpu", "--size", "32", "--updates", "2", "--profile-updates", "2", "--fill", "100"])
    output = capsys.readouterr().out
    assert "32x32 frames; latent batch 8, actor-critic batch 16, sequences of 4 transitions" in output
    part_table = output[output.index("| part |") : output.index("By op")]
    rows = {cells[0]: cells[1:] for cells in (line.strip("|").split("|") for line in part_table.splitlines()[2:] if line)}
    rows = {label.strip(): [cell.strip() for cell in cells] for label, cells in rows.items()}
    labels = [*update_profile.PARTS, update_profile.OPTIMIZER, update_profile.OTHER]
    assert list(rows)[: len(labels)] == labels
    for label in labels:
        forward, backward, total = (float(cell) for cell in rows[label][1:4])
        assert all(math.isfinite(value) and value >= 0.0 for value in (forward, backward, total)), (label, rows[label])
        assert abs(forward + backward - total) <= 0.011, (label, rows[label])
    total_mflop = float(rows["update, profiled"][0])
    assert total_mflop > 0.0
    part_mflops = [float(rows[label][0]) for label in labels if rows[label][0] != "-"]
    assert min(part_mflops) >= 0.0 and abs(sum(part_mflops) - total_mflop) <= 0.1 * len(part_mflops)
    # The learned parts do the arithmetic: every one of them has FLOPs
    assert all(float(rows[label][0]) > 0.0 for label in update_profile.PARTS)
    assert "| aten::" in output[output.index("By op") :]
