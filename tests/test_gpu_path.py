"""
The GPU path, shown on a CPU: bursts on the ``meta`` device standing in for CUDA (no CPU tensor made, no host read, no
CPU/device mix inside a burst), a model loaded onto it, the compiled steps' graphs traced with a custom backend (no
input that a CUDA graph would copy is written), compiled against eager bfloat16, TF32 and bfloat16 and the layout by
device, and ``benchmarks/tools/gpu_check.sh --cpu``.
"""

import os
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
import torch as th
from stable_baselines3.common.logger import configure
from torch._dynamo.backends.common import aot_autograd
from torch._functorch.aot_autograd import make_boxed_func
from torch._guards import TracingContext
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves

from sb3_dsslac import DSSLAC
from sb3_dsslac.engine.bursts import split_windows
from sb3_dsslac.nn import numerics
from sb3_dsslac.nn.latent import LatentModel, channels_last_is_faster
from tests.synthetic_envs import HazardPointEnv
from tests.test_dsslac import SMALL_POLICY, small_model
from tests.test_fast_path import image_batch

REPO = Path(__file__).resolve().parents[1]


class StandInDevice(TorchDispatchMode):
    """
    Watches what runs on the ``meta`` device as a GPU would see it. Inside a burst (``inside``), notes every op that
    makes a CPU tensor or mixes a CPU tensor of one or more dims with a device one (a 0-d CPU tensor is a scalar to
    PyTorch, read on the host), and every copy to the host. A copy of a ``meta`` tensor to the host anywhere (a
    burst's one read at its end) is answered with -1s, counted in ``host_reads``: a meta tensor has no values.
    """

    def __init__(self) -> None:
        super().__init__()
        self.inside = False
        self.violations: list[str] = []
        self.host_reads = 0
        self.ops = 0

    def __torch_dispatch__(self, func: Any, types: Any, args: tuple = (), kwargs: dict | None = None) -> Any:
        kwargs = kwargs or {}
        if func is th.ops.aten._to_copy.default and args[0].is_meta and kwargs.get("device") == th.device("cpu"):
            self.host_reads += 1
            if self.inside:
                self.violations.append(f"{func}: a copy to the host")
            return th.full(args[0].shape, -1, dtype=kwargs.get("dtype") or args[0].dtype)
        out = func(*args, **kwargs)
        if self.inside:
            self.ops += 1
            inputs = [value for value in tree_leaves((args, kwargs)) if isinstance(value, th.Tensor)]
            outputs = [value for value in tree_leaves(out) if isinstance(value, th.Tensor)]
            if any(value.device.type == "cpu" for value in outputs):
                self.violations.append(f"{func}: made a CPU tensor")
            elif any(value.is_meta for value in inputs) and any(value.is_cpu and value.dim() > 0 for value in inputs):
                self.violations.append(f"{func}: CPU and device tensors mixed")
        return out


def on_meta(model: DSSLAC, tmp_path: Path, **load_keywords: Any) -> DSSLAC:
    """``model`` saved, then loaded onto the ``meta`` device with its replay buffer, as ``load(device="cuda")`` would."""
    model.save(tmp_path / "model.zip")
    model.save_replay_buffer(tmp_path / "buffer.pkl")
    # Moved to a device of another tensor type, a module's parameters become new objects unless swapped in place, and
    # the optimizers built before the move would hold the old CPU ones; CUDA tensors take the new data in place
    th.__future__.set_swap_module_params_on_conversion(True)
    try:
        loaded = DSSLAC.load(tmp_path / "model.zip", env=model.get_env(), device="meta", **load_keywords)
    finally:
        th.__future__.set_swap_module_params_on_conversion(False)
    loaded.load_replay_buffer(tmp_path / "buffer.pkl")
    loaded.set_logger(configure(None, []))
    return loaded


def watched_bursts(model: DSSLAC, monkeypatch: pytest.MonkeyPatch) -> StandInDevice:
    """A ``StandInDevice`` whose ``inside`` is on while ``model`` runs a burst of updates (pre-training included)."""
    watcher = StandInDevice()
    burst = model.updates.burst

    def watched_burst(*args: Any, **kwargs: Any) -> dict[str, list[th.Tensor]]:
        watcher.inside = True
        try:
            return burst(*args, **kwargs)
        finally:
            watcher.inside = False

    monkeypatch.setattr(model.updates, "burst", watched_burst)
    return watcher


@pytest.mark.parametrize(
    "obs_type, keywords",
    [
        ("pixels", {}),
        ("pixels", {"share_latent_batch": True, "actor_critic_transitions": 2}),
        ("state", {"lagrange": "critic"}),
    ],
    ids=["pixels", "pixels-shared-batch", "state-critic-rule"],
)
def test_bursts_on_a_loaded_meta_model_make_no_host_tensor_and_read_nothing(
    obs_type: str, keywords: dict[str, Any], tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    model = small_model(HazardPointEnv(obs_type=obs_type), learning_starts=10_000, **keywords)
    model.learn(60)  # warm-up data only
    model.lagrange_raw.fill_(0.7)
    meta = on_meta(model, tmp_path)
    assert meta.device.type == "meta" and meta.policy.latent.z1_posterior_init.net[0].weight.is_meta
    assert meta.lagrange_raw.is_cpu and meta.lagrange_multiplier == pytest.approx(model.lagrange_multiplier)

    watcher = watched_bursts(meta, monkeypatch)
    with watcher:
        meta.train(gradient_steps=3, batch_size=meta.batch_size)  # the latent pre-training's burst, then 3 updates
    assert meta.latent_pretrained and meta._n_updates == 3
    assert watcher.violations == [] and watcher.ops > 500
    assert watcher.host_reads == 2  # one at the end of each burst
    assert meta.lagrange_raw.is_cpu
    if meta.lagrange == "critic":  # moved on the device, read back with the burst's statistics (the stand-in's -1)
        assert meta.lagrange_raw.item() == -1.0
    else:
        assert meta.lagrange_raw.item() == pytest.approx(0.7)
    assert meta.logger.name_to_value["train/lagrange_multiplier"] == pytest.approx(meta.lagrange_multiplier)


def test_checkpoints_that_hold_the_multiplier_as_a_torch_variable_still_load(tmp_path, monkeypatch) -> None:
    # Files saved before the multiplier moved into the saved attributes hold it in pytorch_variables.pth
    model = small_model(HazardPointEnv())
    model.lagrange_raw.fill_(0.7)
    torch_save_params = DSSLAC._get_torch_save_params
    monkeypatch.setattr(
        DSSLAC, "_get_torch_save_params", lambda self: (torch_save_params(self)[0], ["log_ent_coef", "lagrange_raw"])
    )
    model.save(tmp_path / "old.zip")
    monkeypatch.undo()
    loaded = DSSLAC.load(tmp_path / "old.zip")
    assert loaded.lagrange_raw.is_cpu and loaded.lagrange_raw.dtype == th.float64
    assert loaded.lagrange_raw.item() == pytest.approx(0.7) and loaded.updates.lagrange_raw is loaded.lagrange_raw


def traced_graph_inputs(monkeypatch: pytest.MonkeyPatch) -> list[tuple[list[th.Tensor], list[th.Tensor]]]:
    """
    Make ``torch.compile`` trace with AOTAutograd and run the traced graphs as they are (no Inductor); the list it
    returns fills, per graph, with the inputs that are neither parameters, buffers nor marked static (a CUDA graph
    copies those in at every replay), and those of them that the graph writes (which make CUDA graph trees skip it).
    """
    graphs: list[tuple[list[th.Tensor], list[th.Tensor]]] = []

    def inspecting_backend(graph_module: th.fx.GraphModule, example_inputs: list[th.Tensor], **kwargs: Any) -> Any:
        def inspect(graph: th.fx.GraphModule, inputs: list[th.Tensor]) -> Any:
            metadata = TracingContext.get().fw_metadata
            static = set(metadata.static_input_indices)
            dynamic = [i for i, value in enumerate(example_inputs) if isinstance(value, th.Tensor) and i not in static]
            written = [i for i in dynamic if metadata.input_info[i].mutates_data]
            graphs.append(([example_inputs[i] for i in dynamic], [example_inputs[i] for i in written]))
            return make_boxed_func(graph.forward)

        return aot_autograd(fw_compiler=inspect)(graph_module, example_inputs)

    compile_function = th.compile
    monkeypatch.setattr(
        th, "compile", lambda step, **options: compile_function(step, backend=inspecting_backend, fullgraph=True)
    )
    return graphs


def test_the_compiled_steps_write_only_static_inputs(monkeypatch) -> None:
    # CUDA graph trees skip a graph that writes an input that is not a parameter, buffer or static address (saying so
    # only under TORCH_LOGS=perf_hints): the step would launch kernel by kernel. Sequences of 1: the same graphs, shorter
    graphs = traced_graph_inputs(monkeypatch)
    model = small_model(HazardPointEnv(), learning_starts=10_000, sequence_length=1, compile_updates=True)
    model.learn(40)  # warm-up data only
    model.latent_pretrained = True
    updates, step = model.updates, model.updates.step
    indices = model.replay_buffer.sample_indices(2, model.latent_batch_size + model.batch_size)
    (batch, _), (_, waiting) = (split_windows(model.replay_buffer.gather(indices[k]), model.latent_batch_size) for k in (1, 0))
    updates.begin_burst(model.current_lagrange_learning_rate)
    updates.run_step(step.full_step, batch, waiting)
    updates.run_step(step.last_actor_critic_step, waiting)

    assert len(graphs) == 2
    named = {id(tensor): name for name, tensor in vars(step.guard).items() if isinstance(tensor, th.Tensor)}
    named |= {id(model.log_ent_coef): "log_ent_coef", id(step.lagrange_raw): "lagrange_raw"}
    for optimizer in step.optimizers:
        named |= {id(value): f"optimizer state {key}" for state in optimizer.state.values() for key, value in state.items()}
    for _, written in graphs:
        assert [named.get(id(tensor), tuple(tensor.shape)) for tensor in written] == []


def test_the_compiled_rollout_runs_in_eager_dtypes_under_bf16_autocast() -> None:
    # The rollout's noise and recurrent steps are float32 under autocast, compiled or not (bfloat16 is for the
    # convolutions). Dynamo alone (backend "eager") traces the compiled branch without Inductor's rounding
    th.manual_seed(0)
    model = LatentModel((3, 32, 32), 2, feature_dim=16, z1_dim=4, z2_dim=8, hidden_units=(32, 32))
    batch = image_batch(32)

    def posterior(observations: th.Tensor, actions: th.Tensor) -> Any:
        return model.posterior(model.encode(observations), actions)

    def seeded_run(posterior: Any, loss: Any) -> tuple[Any, th.Tensor]:
        th.manual_seed(3)
        rollout = posterior(*batch[:2])
        th.manual_seed(3)
        return rollout, loss(*batch)[0]

    with th.autocast("cpu", dtype=th.bfloat16):
        rollout, loss = seeded_run(posterior, model.loss)
        compiled = (th.compile(function, backend="eager", fullgraph=True) for function in (posterior, model.loss))
        compiled_rollout, compiled_loss = seeded_run(*compiled)
    assert [value.dtype for value in compiled_rollout] == [value.dtype for value in rollout] == [th.float32] * 4
    for name, value, compiled_value in zip(rollout._fields, rollout, compiled_rollout, strict=True):
        th.testing.assert_close(compiled_value, value, rtol=1e-5, atol=1e-5, msg=name)
    assert compiled_loss.dtype == loss.dtype == th.float32
    th.testing.assert_close(compiled_loss, loss, rtol=1e-4, atol=1e-4)


@pytest.fixture
def restore_fp32_precision():
    """Put back the process-wide float32 precision switches that a test sets."""
    switches = (th.backends.cuda.matmul, th.backends.cudnn.conv)
    previous = [switch.fp32_precision for switch in switches]
    yield switches
    for switch, precision in zip(switches, previous, strict=True):
        switch.fp32_precision = precision


@pytest.mark.parametrize("user_precision", ["tf32", "ieee"])
def test_tf32_scope_after_the_new_precision_api_was_set(user_precision: str, restore_fp32_precision) -> None:
    matmul, conv = restore_fp32_precision
    matmul.fp32_precision = user_precision  # as PyTorch recommends now; torch 2.13 then raises on a legacy allow_tf32
    with numerics.tf32_matmul(True):
        assert (matmul.fp32_precision, conv.fp32_precision) == ("tf32", "tf32")
    assert matmul.fp32_precision == user_precision


def test_native_bf16_is_the_models_gpus_own(monkeypatch) -> None:
    capabilities = {0: (7, 0), 1: (9, 0)}  # a V100 (bfloat16 emulated, which is_bf16_supported counts), an H100
    asked = []

    def capability(device: th.device) -> tuple[int, int]:
        asked.append(device)
        return capabilities[device.index]

    monkeypatch.setattr(th.cuda, "get_device_capability", capability)
    monkeypatch.setattr(th.cuda, "is_bf16_supported", lambda including_emulation=True: True)
    assert not numerics.has_native_bf16(th.device("cuda", 0))
    assert numerics.has_native_bf16(th.device("cuda", 1))
    assert asked == [th.device("cuda", 0), th.device("cuda", 1)]
    assert not numerics.has_native_bf16(th.device("meta"))


def test_the_layout_is_chosen_for_the_models_device(monkeypatch) -> None:
    monkeypatch.setattr(th.backends.cpu, "get_cpu_capability", lambda: "AVX512")  # narrow widths channels-last here
    narrow, thesis = (8, 16, 32, 64), (32, 64, 128, 256)
    assert channels_last_is_faster(narrow, th.device("cpu")) and channels_last_is_faster(thesis, th.device("cpu"))
    assert not channels_last_is_faster(narrow, th.device("cuda")) and channels_last_is_faster(thesis, th.device("cuda"))
    policy_kwargs = {**SMALL_POLICY, "image_channels": (4, 8, 8, 16)}
    for device, channels_last in (("cpu", True), ("meta", False)):
        model = small_model(HazardPointEnv(obs_type="pixels"), policy_kwargs=policy_kwargs, device=device)
        latent = model.policy.latent
        assert latent.channels_last == model.replay_buffer.channels_last_frames == channels_last, device
        assert latent.encoder[0].weight.is_contiguous() != channels_last, device


def test_a_pre_release_of_torch_2_13_compiles_the_updates(monkeypatch) -> None:
    # NVIDIA's containers number their builds so ("2.13.0a0+..."), which compare below 2.13 as versions
    monkeypatch.setattr(th, "__version__", "2.13.0a0+5228986c39.nv26.03")
    model = small_model(HazardPointEnv(), compile_updates=True)
    assert set(model.updates.compiled_steps) == {"full_step", "last_actor_critic_step"}


def test_gpu_check_runs_its_cpu_dry_mode(tmp_path) -> None:
    # The same script as on a GPU machine, every CUDA step skipped and said so, at small sizes
    environment = {**os.environ, "OUT_DIR": str(tmp_path), "PYTHON": sys.executable}
    result = subprocess.run(
        ["bash", "benchmarks/tools/gpu_check.sh", "--cpu"],
        cwd=REPO,
        env=environment,
        capture_output=True,
        text=True,
        timeout=600,
    )
    assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
    tables = (tmp_path / "tables.md").read_text()
    assert tables.count("| pass |") == 4 and tables.count("skipped (no CUDA: --cpu)") == 2 and "FAIL" not in tables
    assert "| small | cpu | False | no (eager) |" in tables
