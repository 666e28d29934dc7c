"""benchmarks/tools/update_profile.py: the by-part table of one DS-SLAC update at the smallest pixel shapes."""

import math
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]


def test_update_profile_lists_every_part_with_its_flops_and_times(monkeypatch, capsys) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks" / "tools"))
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
    monkeypatch.syspath_prepend(str(REPO / "benchmarks" / "tools"))
    import update_profile

    assert update_profile.arithmetic_kind("aten::mkldnn_convolution") == "convolutions"
    assert update_profile.arithmetic_kind("aten.convolution_backward") == "convolutions"
    assert update_profile.arithmetic_kind("aten.addmm") == "matrix products"
    assert update_profile.arithmetic_kind("aten::bmm") == "matrix products"
    assert update_profile.arithmetic_kind("aten::add") is None
    assert update_profile.arithmetic_kind("aten::mm_backward") is None


def test_free_convolutions_keep_each_layers_shapes_layouts_and_parameters(monkeypatch) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks" / "tools"))
    import torch as th
    import update_profile

    from sb3_dsslac.nn.convolutions import SubpixelConvTranspose2d

    layers = [
        th.nn.Conv2d(3, 8, 5, stride=2, padding=2),
        th.nn.Conv2d(8, 16, 3, stride=2, padding=1),
        th.nn.ConvTranspose2d(16, 8, 3, stride=2, padding=1, output_padding=1),
        SubpixelConvTranspose2d(8, 3, 5, stride=2, padding=2, output_padding=1),
    ]
    for layer in layers:
        for layout in (th.contiguous_format, th.channels_last):
            x = th.rand(2, layer.in_channels, 16, 16).contiguous(memory_format=layout).requires_grad_()
            free = update_profile.FreeConvolution(layer)
            out = free(x)
            assert out.shape == layer(x).shape and out.is_contiguous(memory_format=layout), (layer, layout)
            assert free.weight is layer.weight and free.bias is layer.bias
            out.sum().backward()
            assert x.grad is not None and layer.weight.grad is not None and layer.bias.grad is not None
            layer.zero_grad()


def test_the_floor_measures_the_convolutions_with_free_stand_ins(monkeypatch, capsys) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks" / "tools"))
    import update_profile

    arguments = ["--preset", "cpu", "--size", "32", "--updates", "2", "--profile-updates", "2", "--fill", "100"]
    update_profile.main([*arguments, "--free-convolutions"])
    output = capsys.readouterr().out
    floor_table = output[output.index("| | ms/update |") :]
    rows = {
        cells[0].strip(): float(cells[1])
        for cells in (line.strip("|").split("|") for line in floor_table.splitlines()[2:] if line.startswith("|"))
    }
    update_ms, free_ms = rows["update"], rows["update with free convolutions"]
    assert free_ms > 0.0 and abs(rows["of which convolutions"] - (update_ms - free_ms)) <= 0.011
    expected_rest = max(0.0, free_ms - rows["of which matrix products"])
    assert abs(rows["the rest (elementwise ops, copies, optimizer, Python)"] - expected_rest) <= 0.011


def test_free_convolutions_replace_the_layers_that_run_convolution_ops(monkeypatch) -> None:
    monkeypatch.syspath_prepend(str(REPO / "benchmarks" / "tools"))
    import update_profile

    from sb3_dsslac import DSSLAC
    from tests.synthetic_envs import HazardPointEnv
    from tests.test_dsslac import SMALL

    model = DSSLAC("LatentPolicy", HazardPointEnv(obs_type="pixels", size=64), **SMALL)
    latent = model.policy.latent
    parameters = [id(parameter) for parameter in latent.parameters()]
    update_profile.free_convolutions(model)
    kinds = [type(layer).__name__ for network in (latent.encoder, latent.decoder) for layer in network]
    # 64x64: four stride-2 convolutions, the dense 4x4 one, the dense 1x1 transposed one, three stride-2 transposed ones
    # and the sub-pixel output layer
    assert kinds.count("FreeConvolution") == 8
    assert kinds.count("DenseConv2d") == 1 and kinds.count("DenseConvTranspose2d") == 1
    assert [id(parameter) for parameter in latent.parameters()] == parameters  # the optimizer's, in its order
