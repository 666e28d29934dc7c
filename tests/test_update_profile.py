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
    floor_table = output[output.index("| | ms/update |") :]
    floor_rows = {
        cells[0].strip(): [cell.strip() for cell in cells[1:]]
        for cells in (line.strip("|").split("|") for line in floor_table.splitlines()[2:] if line.startswith("|"))
    }
    update_ms = float(floor_rows["update"][0])
    kinds_ms = [float(floor_rows[f"of which {kind}"][0]) for kind in update_profile.ARITHMETIC_KINDS]
    rest_ms = float(floor_rows["the rest (elementwise ops, copies, optimizer, Python)"][0])
    # The convolutions (encoder, decoder) and matrix products (heads, critics) take time, and with the rest make the update
    assert min(kinds_ms) > 0.0 and rest_ms >= 0.0
    assert abs(sum(kinds_ms) + rest_ms - update_ms) <= 0.03 or rest_ms == 0.0
    (floor_ms,) = (float(cells[0]) for label, cells in floor_rows.items() if label.startswith("floor:"))
    assert rest_ms < floor_ms


def test_arithmetic_kind_names_the_profilers_and_the_flop_counters_ops(monkeypatch) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks"))
    import update_profile

    assert update_profile.arithmetic_kind("aten::mkldnn_convolution") == "convolutions"
    assert update_profile.arithmetic_kind("aten.convolution_backward") == "convolutions"
    assert update_profile.arithmetic_kind("aten.addmm") == "matrix products"
    assert update_profile.arithmetic_kind("aten::bmm") == "matrix products"
    assert update_profile.arithmetic_kind("aten::add") is None
    assert update_profile.arithmetic_kind("aten::mm_backward") is None
