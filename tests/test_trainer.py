"""Trainer parts without processes: model shapes, targets, VGG weights, data partition."""

from __future__ import annotations

import dataclasses
import itertools
import time
from types import SimpleNamespace as NS

import numpy as np
import pytest
import torch
import torch.nn.functional as F

from render_jobs.tonemap import tonemap as numpy_tonemap
from trainer import runfiles
from trainer.model import ModelConfig, NeuralRenderer, count_parameters, fold_batchnorm
from trainer.targets import Tonemap, light_vector, model_inputs
from trainer.training.config import TrainConfig
from trainer.training.data import epoch_order, rank_batches, steps_left, worker_batches
from trainer.training.losses import MissingWeightsError, RendererLoss, load_vgg, vgg16_relu3_3
from trainer.training.train import epoch_end_saves


def vgg_weights_file(path, seed: int = 0):
    """A torchvision-format VGG16 state dict (random weights; classifier keys included)."""
    torch.manual_seed(seed)
    state = {f"features.{k}": v for k, v in vgg16_relu3_3().state_dict().items()}
    state["features.17.weight"] = torch.zeros(512, 256, 3, 3)  # beyond relu3_3: ignored
    state["classifier.0.weight"] = torch.zeros(8, 8)
    torch.save(state, path)
    return path


# ---- model ----------------------------------------------------------------------------------


@pytest.mark.parametrize("res", [64, 128, 400])
def test_output_shape_and_range(res):
    model = NeuralRenderer(ModelConfig(resolution=res)).eval()
    with torch.no_grad():
        out = model(torch.rand(2, 10, res, res), torch.rand(2, 4))
    assert out.shape == (2, 3, res, res)
    assert float(out.min()) >= 0 and float(out.max()) <= 1


def test_ablations_and_twelve_channels():
    full = NeuralRenderer(ModelConfig(resolution=64))
    flat = NeuralRenderer(ModelConfig(resolution=64, skips=False))
    thin = NeuralRenderer(ModelConfig(resolution=64, width=16, roughness_channels=3))
    assert count_parameters(flat) < count_parameters(full)
    assert count_parameters(thin) < count_parameters(flat)
    assert thin(torch.rand(1, 12, 64, 64), torch.rand(1, 4)).shape == (1, 3, 64, 64)
    assert flat(torch.rand(1, 10, 64, 64), torch.rand(1, 4)).shape == (1, 3, 64, 64)
    # the light encoder's plane is the bottleneck's size, replicated to 128 channels
    plane = full.light(torch.rand(3, 4))
    assert plane.shape == (3, 128, 4, 4) and torch.equal(plane[:, 0], plane[:, 127])


def test_light_changes_the_image():
    model = NeuralRenderer(ModelConfig(resolution=64)).eval()
    maps = torch.rand(1, 10, 64, 64)
    with torch.no_grad():
        a = model(maps, torch.tensor([[0.0, 0.0, 1.0, 0.2]]))
        b = model(maps, torch.tensor([[0.7, 0.0, 0.7, 0.9]]))
    assert not torch.allclose(a, b)


def test_glorot_init():
    model = NeuralRenderer(ModelConfig(resolution=64, width=16))
    conv = model.encoder[1][0].weight.detach()  # 16 → 32 channels, 3x3
    bound = (6 / (16 * 9 + 32 * 9)) ** 0.5
    assert float(conv.abs().max()) <= bound
    assert float(conv.std()) == pytest.approx(bound / 3**0.5, rel=0.1)


@pytest.mark.parametrize("decoder_convs", [1, 2])
def test_folded_batchnorm_gives_the_same_image(decoder_convs):
    model = NeuralRenderer(ModelConfig(resolution=64, width=16, decoder_convs=decoder_convs))
    model.train()
    for _ in range(3):  # running statistics that are not the identity
        model(torch.rand(4, 10, 64, 64) * 2, torch.rand(4, 4))
    model.eval()
    x, light = torch.rand(2, 10, 64, 64), torch.rand(2, 4)
    folded = fold_batchnorm(model)
    assert not any(isinstance(m, torch.nn.BatchNorm2d) for m in folded.modules())
    with torch.no_grad():
        torch.testing.assert_close(folded(x, light), model(x, light), atol=1e-5, rtol=1e-4)


def test_decoder_convs_add_a_block_at_each_level():
    """Two blocks a decoder level: more weights, the same image shape; the paper's form (one)
    has no keys of theirs, so its checkpoints load."""
    one = NeuralRenderer(ModelConfig(resolution=64, width=16))
    two = NeuralRenderer(ModelConfig(resolution=64, width=16, decoder_convs=2))
    assert not any(k.startswith("refine.") for k in one.state_dict())
    assert one.config.plain and not two.config.plain
    # each level's extra block is a c -> c 3x3 conv + norm (c = 128, 64, 32, 16 at width 16)
    extra = sum(c * c * 9 + 2 * c for c in (128, 64, 32, 16))
    assert count_parameters(two) - count_parameters(one) == extra
    assert two(torch.rand(2, 10, 64, 64), torch.rand(2, 4)).shape == (2, 3, 64, 64)
    with pytest.raises(ValueError, match="decoder_convs must be at least 1, not 0"):
        ModelConfig(resolution=64, decoder_convs=0)


@pytest.mark.parametrize("res", [0, 40, 100, 401])
def test_resolution_not_divisible_by_16(res):
    with pytest.raises(ValueError, match=f"resolution {res} is not a (positive )?multiple of 16"):
        ModelConfig(resolution=res)


def test_input_shape_errors_name_the_input():
    model = NeuralRenderer(ModelConfig(resolution=64))
    with pytest.raises(ValueError, match=r"maps have shape \(1, 10, 32, 32\)"):
        model.check_inputs(torch.rand(1, 10, 32, 32), torch.rand(1, 4))
    with pytest.raises(ValueError, match=r"light has shape \(1, 3\)"):
        model.check_inputs(torch.rand(1, 10, 64, 64), torch.rand(1, 3))


# ---- targets --------------------------------------------------------------------------------


def test_tonemap_is_the_preview_curve():
    x = np.random.default_rng(0).gamma(1.0, 0.5, (1, 3, 16, 16)).astype(np.float32)
    ours = Tonemap()(torch.from_numpy(x).half()).numpy()[0]
    np.testing.assert_allclose(ours, numpy_tonemap(x[0].astype(np.float16)), atol=1e-5)
    assert Tonemap.from_dict(Tonemap(exposure=0.5).to_dict()) == Tonemap(exposure=0.5)


def test_model_inputs_and_light_vector():
    packed = torch.arange(11 * 4, dtype=torch.uint8).view(1, 11, 2, 2)
    x = model_inputs(packed)
    assert x.shape == (1, 10, 2, 2) and torch.allclose(x * 255, packed[:, :10].float())
    x12 = model_inputs(packed, 3)
    assert torch.equal(x12[:, 6], x12[:, 8]) and torch.equal(x12[:, 9:], x[:, 7:])
    v = light_vector((0.0, 0.0, 2.0), 3.0)
    np.testing.assert_allclose(v, [0, 0, 1, 0.3], atol=1e-7)
    with pytest.raises(ValueError, match="zero vector"):
        light_vector((0, 0, 0), 3)


# ---- perceptual loss ------------------------------------------------------------------------


def test_vgg_loads_torchvision_format(tmp_path):
    path = vgg_weights_file(tmp_path / "vgg16.pth")
    vgg = load_vgg(path)
    state = torch.load(path, weights_only=True)
    assert torch.equal(vgg[14].weight, state["features.14.weight"])  # conv3_3
    assert not any(p.requires_grad for p in vgg.parameters())
    loss = RendererLoss(vgg)
    a, b = torch.rand(2, 3, 32, 32), torch.rand(2, 3, 32, 32)
    assert float(loss(a, a)) == 0 and float(loss(a, b)) > float(RendererLoss()(a, b))


def test_vgg_found_in_the_hub_cache(tmp_path, monkeypatch):
    monkeypatch.setenv("TORCH_HOME", str(tmp_path))
    with pytest.raises(MissingWeightsError, match="--vgg-weights FILE .* or train with --loss l1"):
        load_vgg()
    (tmp_path / "hub" / "checkpoints").mkdir(parents=True)
    vgg_weights_file(tmp_path / "hub" / "checkpoints" / "vgg16-397923af.pth")
    assert isinstance(load_vgg(), torch.nn.Sequential)


def test_bad_vgg_files(tmp_path):
    with pytest.raises(MissingWeightsError, match="does not exist"):
        load_vgg(tmp_path / "nope.pth")
    (tmp_path / "junk.pth").write_bytes(b"not a torch file")
    with pytest.raises(MissingWeightsError, match="junk.pth: not a readable torch state dict"):
        load_vgg(tmp_path / "junk.pth")
    torch.save({"features.0.weight": torch.zeros(1)}, tmp_path / "other.pth")
    with pytest.raises(MissingWeightsError, match="other.pth: not VGG16 weights"):
        load_vgg(tmp_path / "other.pth")


# ---- data partition: pure functions of integers ---------------------------------------------


def test_epoch_order_is_a_seeded_shard_shuffle():
    groups = [np.arange(i * 5, i * 5 + 5) for i in range(8)]
    a = epoch_order(groups, seed=1, epoch=0, buffer=5)
    assert sorted(a.tolist()) == list(range(40))
    assert np.array_equal(a, epoch_order(groups, seed=1, epoch=0, buffer=5))
    assert not np.array_equal(a, epoch_order(groups, seed=1, epoch=1, buffer=5))
    assert not np.array_equal(a, epoch_order(groups, seed=2, epoch=0, buffer=5))
    # with a buffer of one shard, each window of 5 is one whole shard, shuffled inside
    windows = [set(a[i : i + 5] // 5) for i in range(0, 40, 5)]
    assert all(len(w) == 1 for w in windows) and a[:5].tolist() != sorted(a[:5].tolist())
    assert epoch_order([], 0, 0, 4).size == 0


CASES = list(itertools.product([1, 7, 24, 50], [1, 2, 3, 8], [1, 4], [0, 1, 3]))


@pytest.mark.parametrize(("n", "world", "batch", "workers"), CASES)
def test_ranks_and_workers_cover_each_position_once(n, world, batch, workers):
    seen = []
    counts = []
    for rank in range(world):
        mine = rank_batches(n, world, rank, batch)
        counts.append(len(mine))
        assert len(mine) in (steps_left(n, world, batch), steps_left(n, world, batch) - 1)
        # the DataLoader's round-robin over workers gives the rank's batches back in order
        per_worker = [list(worker_batches(len(mine), workers, w)) for w in range(max(workers, 1))]
        merged = [b for group in itertools.zip_longest(*per_worker) for b in group if b is not None]
        assert merged == list(range(len(mine)))
        seen += [p for r in mine for p in r]
    assert sorted(seen) == list(range(n))  # no overlap, no gap
    assert max(counts) - min(counts) <= 1


@pytest.mark.parametrize(
    ("world", "batch", "k", "new_world"), [(2, 3, 2, 2), (4, 2, 1, 3), (1, 5, 3, 2)]
)
def test_resume_continues_exactly_even_with_another_world_size(world, batch, k, new_world):
    n = 37
    first = [p for rank in range(world) for r in rank_batches(n, world, rank, batch)[:k] for p in r]
    assert sorted(first) == list(range(k * world * batch))  # k full steps = a prefix
    start = k * world * batch
    rest = [
        p
        for rank in range(new_world)
        for r in rank_batches(n, new_world, rank, batch, start)
        for p in r
    ]
    assert sorted(first + rest) == list(range(n))
    # the same world size resumes with exactly the batches it would have read
    for rank in range(world):
        assert rank_batches(n, world, rank, batch)[k:] == rank_batches(n, world, rank, batch, start)


def test_bad_partition_arguments():
    with pytest.raises(ValueError, match="bad partition"):
        rank_batches(10, 2, 2, 1)
    with pytest.raises(ValueError, match="shuffle buffer"):
        epoch_order([np.arange(3)], 0, 0, 0)


@pytest.mark.parametrize("size", [1, 2, 3, 25])
def test_upconv_is_upsampling_then_convolution(size):
    from trainer.rendering.fastnet import UpConv, ring

    z = torch.randn(2, 6, size, size, dtype=torch.float64)
    w = torch.randn(5, 6, 3, 3, dtype=torch.float64)
    want = F.conv2d(F.interpolate(z, scale_factor=2, mode="bilinear"), w, padding=1)
    up = UpConv(w)
    got = up(z)
    assert got.shape == want.shape
    torch.testing.assert_close(got, want, atol=1e-12, rtol=0)
    assert not hasattr(up, "zero_side")  # the edge ring's weights are made when asked for
    up.set_ring(edge=True)  # zero-padded phases, the rings two deep as corrections from z
    torch.testing.assert_close(up(z), want, atol=1e-12, rtol=0)
    up.set_ring(edge=True, fold=True)  # that correction as one product
    torch.testing.assert_close(up(z), want, atol=1e-12, rtol=0)
    with pytest.raises(ValueError, match="fold is a form of the edge ring"):
        up.set_ring(fold=True)
    with pytest.raises(ValueError, match="the ring needs a square input, not 3x4"):
        ring(torch.randn(1, 6, 3, 4), up.ring, torch.zeros(1, 5, 6, 8))
    with pytest.raises(ValueError, match="the ring needs a square input, not 3x4"):
        up(torch.randn(1, 6, 3, 4, dtype=torch.float64))


@pytest.mark.parametrize(
    "cfg",
    [
        ModelConfig(resolution=16, width=8),
        ModelConfig(resolution=64, width=16),
        ModelConfig(resolution=64, width=16, skips=False, roughness_channels=3),
        ModelConfig(resolution=128, width=8),
    ],
)
@pytest.mark.parametrize("align", [1, 8])
def test_subpixel_rewrite_gives_the_same_image(cfg, align):
    """Exact in fp32 in each of its forms, with channel counts padded to multiples of 8 or
    not; the padded input channels' values do not matter, and maps with the model's own
    channel count are padded inside."""
    from trainer.rendering.fastnet import SubpixelRenderer

    model = NeuralRenderer(cfg).train()
    r, c = cfg.resolution, cfg.in_channels
    for _ in range(2):  # running statistics that are not the identity
        model(torch.rand(3, c, r, r) * 2, torch.rand(3, 4))
    model.eval()
    fast = SubpixelRenderer(fold_batchnorm(model), align)
    fast.to(memory_format=torch.channels_last)
    colours = fast.levels[-1].up.phases.weight.shape[0] // 4  # x4 phases before pixel_shuffle
    widths = [fast.in_channels, fast.fuse.weight.shape[1], colours]
    # aligned: 4 colours x 4 phases (16 channels) for the output convolution
    assert widths == ([c, 8 * cfg.width + 1, 3] if align == 1 else [16, 8 * cfg.width + 8, 4])
    x, light = torch.rand(2, c, r, r), torch.rand(2, 4)
    extra = torch.rand(2, fast.in_channels - c, r, r) * 100
    cl = torch.channels_last
    with torch.no_grad():
        want = model(x, light)
        got = fast(x.contiguous(memory_format=cl), light)
        got_wide = fast(torch.cat([x, extra], 1).contiguous(memory_format=cl), light)
    assert got.shape == want.shape
    torch.testing.assert_close(got, want, atol=1e-5, rtol=0)
    torch.testing.assert_close(got_wide, want, atol=1e-5, rtol=0)
    with torch.no_grad():  # the rings as corrections from the edges, on zero-padded phases
        got_edges = fast.rings(edge=True)(x.contiguous(memory_format=cl), light)
    torch.testing.assert_close(got_edges, want, atol=1e-5, rtol=0)
    with torch.no_grad():  # and the ReLUs after convolutions in one operator with them
        got_fused = fast.fuse_relus()(x.contiguous(memory_format=cl), light)
    torch.testing.assert_close(got_fused, want, atol=1e-5, rtol=0)
    with torch.no_grad():  # each ring one product, the light encoder as sums
        fast.rings(edge=True, fold=True).light_sums()
        got_folded = fast(x.contiguous(memory_format=cl), light)
    torch.testing.assert_close(got_folded, want, atol=1e-5, rtol=0)
    with pytest.raises(ValueError, match="fold the BatchNorm first"):
        SubpixelRenderer(model)


def test_bf16_fast_networks_stay_close_to_fp32():
    """The networks the CUDA benchmark rows capture (trainer.rendering.infer.fast_network: BatchNorm
    folded, bf16 weights, channels_last; plain, sub-pixel with its channels aligned or not,
    with its rings as edge corrections, the fastest form among them), run here on CPU: bf16
    images stay within 0.02 of fp32, the rewrite no further off than the original."""
    from trainer.rendering.infer import FASTEST, fast_network

    torch.manual_seed(0)
    model = NeuralRenderer(ModelConfig(resolution=64)).eval()
    x, light = torch.rand(2, model.config.in_channels, 64, 64), torch.rand(2, 4)
    with torch.no_grad():
        want = model(x, light)
        xb = x.to(torch.bfloat16).contiguous(memory_format=torch.channels_last)
        nets = {
            "plain": {},
            "subpixel": {"subpixel": True},
            "unaligned": {"subpixel": True, "align": 1},
            "edge ring": {"subpixel": True, "edge_ring": True},
            "edge ring, conv+ReLU": {"subpixel": True, "edge_ring": True, "conv_relu": True},
            "edge ring, conv+ReLU, light sums": {
                "subpixel": True,
                "edge_ring": True,
                "conv_relu": True,
                "light_sums": True,
            },
            "edge ring, conv+ReLU, light sums, one-product ring": {
                "subpixel": True,
                "edge_ring": True,
                "conv_relu": True,
                "light_sums": True,
                "fold_ring": True,
            },
        }
        errors = {
            name: (fast_network(model, **kw)(xb, light.bfloat16()).float() - want).abs().max()
            for name, kw in nets.items()
        }
    # the fastest form is among those checked here (uncompiled)
    fastest = nets["edge ring, conv+ReLU, light sums, one-product ring"]
    assert fastest | {"compile": True} == FASTEST
    plain = errors.pop("plain")
    assert 0 < plain < 0.02, errors
    for name, err in errors.items():
        assert err < max(2 * plain, 0.01), (name, float(err), float(plain))


def test_the_light_mlp_as_sums_gives_its_linear_layers_numbers_in_one_kernel_a_layer():
    """trainer.rendering.fastnet.SummedMLP: the light encoder's Linear + Tanh layers as products and
    sums, in fp32 for any input dtype; ``light_sums`` switches a rewrite's encoder both ways;
    an MLP of another shape is refused."""
    from trainer.model import fold_batchnorm
    from trainer.rendering.fastnet import SubpixelRenderer, SummedMLP

    torch.manual_seed(0)
    model = NeuralRenderer(ModelConfig(resolution=64)).eval()
    mlp, light = model.light.mlp, torch.rand(3, 4)
    with torch.no_grad():
        torch.testing.assert_close(SummedMLP(mlp)(light), mlp(light), atol=1e-6, rtol=0)
        half = SummedMLP(mlp.to(torch.bfloat16))(light.bfloat16())
        assert half.dtype == torch.bfloat16
        assert (half.float() - mlp.float()(light)).abs().max() < 0.02
        net = SubpixelRenderer(fold_batchnorm(model)).light_sums()
        assert isinstance(net.light, SummedMLP)
        assert net.light_sums(False).light is net.mlp
    with pytest.raises(ValueError, match="not a Linear \\+ Tanh MLP"):
        SummedMLP(torch.nn.Sequential(torch.nn.Linear(4, 4), torch.nn.ReLU()))
    # Inductor's plan for it (Triton, planned on this CPU): one fused kernel a layer, no GEMM
    from benchmarks.kernel_plan import launches, plan_source

    summed = SummedMLP(mlp.to(torch.bfloat16))
    plan = launches(plan_source(lambda x, lt: summed(lt), None, light.bfloat16()))
    assert [n.split("_")[0] for n, _ in plan] == ["triton"] * len(summed.layers), plan
    assert all("tanh" in n and "sum" in n for n, _ in plan), plan


def test_conv_relu_is_one_operator_that_compiles_and_gives_convolution_then_relu():
    """trainer.rendering.convrelu.conv_relu (on CUDA one cuDNN call; here conv2d then relu): the
    same
    numbers, its fake implementation's shapes and strides those of the real one
    (``torch.library.opcheck``), traced whole by Dynamo; ``fast_network`` refuses it for the
    original network, which has no such operator."""
    from trainer.rendering.convrelu import conv_relu
    from trainer.rendering.infer import fast_network

    x = torch.randn(2, 8, 9, 9).contiguous(memory_format=torch.channels_last)
    w, b = torch.randn(4, 8, 3, 3), torch.randn(4)
    for stride, bias, inp in ((1, b, x), (2, b, x), (2, None, x.contiguous())):
        want = F.relu(F.conv2d(inp, w, bias, stride, 1))
        got = conv_relu(inp, w, bias, stride)
        assert got.stride() == want.stride()
        torch.testing.assert_close(got, want, atol=0, rtol=0)
        torch.library.opcheck(conv_relu, (inp, w, bias, stride))
    traced = torch.compile(lambda t: conv_relu(t, w, b, 2) * 2, backend="eager", fullgraph=True)
    torch.testing.assert_close(traced(x), 2 * F.relu(F.conv2d(x, w, b, 2, 1)))
    tiny = NeuralRenderer(ModelConfig(resolution=16, width=8))
    with pytest.raises(ValueError, match="conv_relu is a form of the subpixel"):
        fast_network(tiny, conv_relu=True)
    with pytest.raises(ValueError, match="light_sums is a form of the subpixel"):
        fast_network(tiny, light_sums=True)
    with pytest.raises(ValueError, match="edge_ring is a form of the subpixel"):
        fast_network(tiny, edge_ring=True)
    with pytest.raises(ValueError, match="fold_ring is a form of the edge ring"):
        fast_network(tiny, subpixel=True, fold_ring=True)


def test_compile_options_tune_over_cudnn_and_cublas_unless_the_environment_says():
    """trainer.rendering.infer.compile_options: max-autotune always, over cuDNN and cuBLAS alone
    unless the environment names Inductor's backends."""
    from trainer.rendering.infer import TUNED_BACKENDS, compile_options

    base = {"max_autotune": True, "coordinate_descent_tuning": True} | TUNED_BACKENDS
    assert TUNED_BACKENDS == {"max_autotune_conv_backends": "ATEN",
                              "max_autotune_gemm_backends": "ATEN"}  # fmt: skip
    assert compile_options(environ={}) == base
    env = {"TORCHINDUCTOR_MAX_AUTOTUNE_GEMM_BACKENDS": "ATEN,TRITON"}
    assert "max_autotune_gemm_backends" not in compile_options(environ=env)
    assert compile_options(environ=env)["max_autotune_conv_backends"] == "ATEN"


@pytest.mark.parametrize(("align", "edge"), [(1, False), (8, False), (8, True)])
def test_subpixel_network_traces_as_one_graph(align, edge):
    """``--compile`` must see the rewrite whole: Dynamo traces it with ``fullgraph=True``
    (no graph break; the ``eager`` backend, so no C++ or GPU compiler is needed here);
    ``edge``: the rings as corrections from the edges in one product, the ReLUs after
    convolutions in one operator with them and the light encoder as sums."""
    from trainer.rendering.fastnet import SubpixelRenderer

    torch._dynamo.reset()
    model = NeuralRenderer(ModelConfig(resolution=32)).eval()
    net = SubpixelRenderer(fold_batchnorm(model), align)
    net.rings(edge=edge, fold=edge).fuse_relus(edge).light_sums(edge)
    x, light = torch.rand(1, model.config.in_channels, 32, 32), torch.rand(1, 4)
    traced = torch.compile(net, backend="eager", fullgraph=True, dynamic=False)
    with torch.no_grad():
        torch.testing.assert_close(traced(x, light), model(x, light), atol=1e-5, rtol=0)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal on CPU machines")
def test_cuda_graph_path_refuses_a_cpu_model():
    from trainer.rendering.infer import GraphedRenderer

    model = NeuralRenderer(ModelConfig(resolution=64))
    with pytest.raises(RuntimeError, match="CUDA graphs need the model on a CUDA device"):
        GraphedRenderer(model, 1)
    with pytest.raises(RuntimeError, match="CUDA graphs need the model on a CUDA device"):
        GraphedRenderer.fastest(model, 1)


def test_a_renderer_refuses_a_cuda_graph_it_cannot_capture(tmp_path):
    """``Renderer(graph=True)`` (``trainer viewer --cuda-graph``): the paper's network on a
    CUDA device only, and never an exported model; each refusal names why."""
    from trainer.rendering.infer import Renderer, check_graphable
    from trainer.rendering.load import load_renderer
    from trainer.targets import Tonemap
    from trainer.zf import ZsolnaiFeherRenderer

    model = NeuralRenderer(ModelConfig(resolution=32))
    with pytest.raises(ValueError, match="a CUDA graph needs a CUDA device, not cpu"):
        Renderer(model, Tonemap(), torch.device("cpu"), graph=True)
    zf = ZsolnaiFeherRenderer(ModelConfig(resolution=32, arch="zf"))
    with pytest.raises(ValueError, match="paper's network, not from ZsolnaiFeherRenderer"):
        check_graphable(zf, torch.device("cuda"))
    with pytest.raises(ValueError, match="ball.onnx: a CUDA graph is captured from a torch"):
        load_renderer(tmp_path / "ball.onnx", graph=True)


@pytest.mark.skipif(torch.cuda.is_available(), reason="checks the refusal where CUDA is absent")
def test_cuda_is_refused_in_one_line_where_torch_sees_none():
    from trainer.devices import NoCuda, pick_device

    assert pick_device("auto").type == "cpu" and pick_device("cpu").type == "cpu"
    with pytest.raises(NoCuda, match=r"--device cuda: this torch \(.+\) sees no CUDA device"):
        pick_device("cuda")


@pytest.mark.parametrize("resolution", [32, 288])
def test_inference_network_on_cpu_is_the_rewrite_from_its_size_up_and_elsewhere_the_original(
    resolution,
):
    from trainer.rendering.fastnet import SubpixelRenderer
    from trainer.rendering.infer import CPU_SUBPIXEL_FROM, inference_network

    torch.manual_seed(0)
    model = NeuralRenderer(ModelConfig(resolution=resolution, width=4)).eval()
    x, light = torch.rand(2, 10, resolution, resolution), torch.rand(2, 4)
    cpu = inference_network(model, torch.device("cpu"))
    gpu = inference_network(model, torch.device("cuda"))  # chosen, not moved: runs here too
    rewrite = resolution >= CPU_SUBPIXEL_FROM
    assert isinstance(cpu, SubpixelRenderer if rewrite else NeuralRenderer)
    assert isinstance(gpu, NeuralRenderer) and rewrite == (resolution == 288)
    with torch.no_grad():
        want = model(x, light)
        torch.testing.assert_close(
            cpu(x.contiguous(memory_format=torch.channels_last), light), want
        )
        torch.testing.assert_close(gpu(x, light), want)


def test_the_best_checkpoint_outlives_the_rotation_and_is_replaced_whole(tmp_path):
    from trainer import checkpoint

    def state(step):
        return {"model": {"w": torch.full((4,), float(step))}, "step": step}

    first = checkpoint.save(tmp_path, state(1), keep=1)
    (tmp_path / "checkpoints" / ".best.pt.tmp").write_text("left by a killed run")
    best = checkpoint.keep_best(first)
    checkpoint.save(tmp_path, state(2), keep=1)  # drops step 1's file
    assert not first.exists() and [p.name for p in checkpoint.listing(tmp_path)] == [
        "step-00000002.pt"
    ]
    assert torch.load(best, weights_only=True)["step"] == 1
    checkpoint.keep_best(checkpoint.latest(tmp_path))
    assert torch.load(best, weights_only=True)["step"] == 2
    assert sorted(p.name for p in best.parent.iterdir()) == ["best.pt", "step-00000002.pt"]


def test_learning_rate_schedules_are_functions_of_the_step():
    from trainer.training.schedule import lr_at, run_steps

    assert [lr_at(s, 1e-3, "constant", 10) for s in (0, 5, 9)] == [1e-3] * 3
    assert [lr_at(s, 1e-3, "constant", 10, warmup=4) for s in range(5)] == pytest.approx(
        [2.5e-4, 5e-4, 7.5e-4, 1e-3, 1e-3]
    )
    cosine = [lr_at(s, 1.0, "cosine", 12, warmup=2) for s in range(12)]
    assert cosine[:3] == pytest.approx([0.5, 1.0, 1.0])  # warm-up, then the top of the cosine
    assert cosine[7] == pytest.approx(0.5)  # half way down at half the 10 steps after warm-up
    assert (
        all(a > b for a, b in zip(cosine[2:-1], cosine[3:], strict=True)) and 0 < cosine[-1] < 0.03
    )
    assert lr_at(50, 1.0, "cosine", 12) == 0.0  # past the end (a longer resumed run): 0
    with pytest.raises(ValueError, match="unknown learning-rate schedule 'step'"):
        lr_at(3, 1.0, "step", 10)
    assert run_steps(3, None, 7) == 21 and run_steps(3, 5, 7) == 5 and run_steps(1, 50, 7) == 7


def test_a_cosine_resumed_with_another_length_goes_on_from_its_rate():
    from trainer.training.schedule import lr_at, record, resumed_knee

    was = record("cosine", 20, (2, 1.0))  # 2 warm-up steps, then a cosine to step 20
    assert resumed_knee(8, was, 20, 2) == (2, 1.0)  # the same length: the same curve
    assert resumed_knee(1, was, 40, 2) == (2, 1.0)  # the cosine has not begun: a longer one
    knee = resumed_knee(8, was, 40, 2)  # twice as long from step 8
    before = lr_at(8, 1.0, "cosine", 20, 2)
    assert knee == (8, pytest.approx(before)) and 0.5 < before < 1
    after = [lr_at(s, 1.0, "cosine", 40, 2, knee) for s in range(8, 41)]
    assert after[0] == pytest.approx(before) and after[-1] == 0.0  # no jump, down to 0 at 40
    assert all(a > b for a, b in zip(after, after[1:], strict=False))
    assert after[16] == pytest.approx(before / 2)  # half of it half way through the rest
    shorter = resumed_knee(8, was, 12, 2)
    assert lr_at(8, 1.0, "cosine", 12, 2, shorter) == pytest.approx(before)
    assert lr_at(12, 1.0, "cosine", 12, 2, shorter) == 0.0
    assert resumed_knee(20, was, 30, 2) == (20, 0.0)  # resumed past its end: at 0
    again = record("cosine", 40, knee)  # resumed twice: from the second knee on
    assert resumed_knee(10, again, 40, 2) == knee
    assert resumed_knee(10, again, 60, 2) == (10, pytest.approx(after[2]))
    assert resumed_knee(8, record("constant", 20, (0, 1.0)), 20, 2) == (8, 1.0)  # starts now
    assert resumed_knee(8, None, 40, 2) == (2, 1.0)  # a checkpoint with no record


def test_the_weight_average_warms_up_then_keeps_its_decay():
    from trainer.training.ema import WeightAverage, decay_at

    assert [decay_at(n, 0.999) for n in (0, 1, 8)] == pytest.approx([0.1, 2 / 11, 0.5])
    assert decay_at(10**6, 0.999) == 0.999 and decay_at(10**6, 0.5) == 0.5
    torch.manual_seed(0)
    model = torch.nn.Sequential(torch.nn.Conv2d(2, 3, 1), torch.nn.BatchNorm2d(3))
    avg = WeightAverage(model, 0.9)
    assert not avg.model.training and not any(p.requires_grad for p in avg.model.parameters())
    start = {k: v.clone() for k, v in avg.model.state_dict().items()}
    model.train()(torch.randn(4, 2, 5, 5))  # BatchNorm's running statistics and counter move
    with torch.no_grad():
        model[0].weight.add_(1.0)
    avg.update(model)
    now, trained = avg.model.state_dict(), model.state_dict()
    d = decay_at(0, 0.9)  # 0.1: the first update is mostly the trained weights
    for key in ("0.weight", "0.bias", "1.running_mean", "1.running_var"):
        torch.testing.assert_close(now[key], d * start[key] + (1 - d) * trained[key])
    assert now["1.num_batches_tracked"] == trained["1.num_batches_tracked"] == 1  # copied
    assert avg.updates == 1 and not torch.equal(now["0.weight"], trained["0.weight"])
    again = WeightAverage(model, 0.9)  # a resumed run: the kept average and its count
    again.load_state_dict(avg.state_dict())
    assert again.updates == 1 and all(torch.equal(again.model.state_dict()[k], now[k]) for k in now)
    with pytest.raises(ValueError, match="decay must be in"):
        WeightAverage(model, 1.0)


def test_a_checkpoint_renders_with_its_average_unless_told_otherwise():
    from trainer.checkpoint import CheckpointError, weights

    plain = {"model": {"w": 1}, "step": 3}
    kept = {**plain, "ema": {"weights": {"w": 2}, "decay": 0.9, "updates": 3}}
    assert [weights(kept, w) for w in ("auto", "average", "trained")] == [
        {"w": 2},
        {"w": 2},
        {"w": 1},
    ]
    assert [weights(plain, w) for w in ("auto", "trained")] == [{"w": 1}, {"w": 1}]
    with pytest.raises(CheckpointError, match="kept no average of its weights at step 3"):
        weights(plain, "average")
    with pytest.raises(ValueError, match="weights must be one of"):
        weights(kept, "best")


# ---- comparing checkpoints ------------------------------------------------------------------


def test_paired_differences_resample_whole_materials():
    from trainer.intervals import MIN_MATERIALS, paired_difference

    rng = np.random.default_rng(1)
    base = rng.normal(25, 3, 200)
    groups = np.repeat(np.arange(40), 5)[:, None] * [1, 1]  # 40 materials x 5 suns
    same = paired_difference(base, base, groups)
    assert (same["mean"], same["low"], same["high"], same["higher"]) == (0, 0, 0, 0)
    shifted = paired_difference(base, base + 0.5, groups)
    assert shifted["mean"] == pytest.approx(0.5) and shifted["higher"] == 1
    assert shifted["low"] == pytest.approx(0.5) and shifted["high"] == pytest.approx(0.5)
    # a material's suns move together: the interval is that of the 40 materials' means
    # (normal approximation: 1.96 standard errors, the bootstrap's n - 1 over n variance),
    # not the far narrower one of 200 independent samples
    effect = np.repeat(rng.normal(0.3, 1.0, 40), 5)
    d = paired_difference(base, base + effect, groups)
    means = effect.reshape(40, 5)[:, 0]
    half = 1.96 * means.std() / np.sqrt(40)
    assert d["mean"] == pytest.approx(means.mean())
    assert d["low"] < d["mean"] < d["high"]
    assert (d["high"] - d["low"]) / 2 == pytest.approx(half, rel=0.15)
    assert (d["high"] - d["low"]) / 2 > 2 * 1.96 * effect.std() / np.sqrt(200)
    assert paired_difference(base, base + effect, groups) == d  # a fixed seed
    # under MIN_MATERIALS materials: the mean and the share, no interval
    few = paired_difference(base[:10], base[:10] + 1, groups[:10])
    assert few["materials"] == 2 < MIN_MATERIALS and few["low"] is None and few["mean"] == 1
    # materials are (store, material) pairs: material 0 of two stores is two materials
    two = np.array([[0, 0], [0, 0], [1, 0], [1, 0]])
    assert paired_difference(np.zeros(4), np.ones(4), two)["materials"] == 2


def test_a_mean_s_interval_resamples_whole_materials():
    from trainer.intervals import MIN_MATERIALS, cluster_mean, excludes_zero, paired_difference

    rng = np.random.default_rng(2)
    per_material = rng.normal(26.0, 2.0, 30)
    values = np.repeat(per_material, 5) + rng.normal(0, 0.1, 150)  # 30 materials x 5 suns
    groups = np.repeat(np.arange(30), 5)  # materials as plain ints
    m = cluster_mean(values, groups)
    half = 1.96 * per_material.std() / np.sqrt(30)
    assert m["mean"] == pytest.approx(values.mean()) and m["materials"] == 30
    assert m["low"] < m["mean"] < m["high"]
    assert (m["high"] - m["low"]) / 2 == pytest.approx(half, rel=0.2)
    assert excludes_zero(m)  # 26 dB is not 0
    # a paired difference is the interval of the differences' mean
    diff = 0.2 + rng.normal(0, 1, 150)
    d = paired_difference(values, values + diff, groups)
    assert {k: d[k] for k in ("mean", "low", "high", "materials")} == pytest.approx(
        cluster_mean(diff, groups)
    )
    assert d["higher"] == pytest.approx((diff > 0).mean())
    few = cluster_mean(values[:20], groups[:20])
    assert few["materials"] == 4 < MIN_MATERIALS and few["low"] is None
    assert not excludes_zero(few)
    assert cluster_mean([], np.zeros(0, np.int64)) == {
        "mean": None, "materials": 0, "low": None, "high": None
    }  # fmt: skip


def test_comparison_labels_name_the_weights_only_where_paths_repeat():
    from trainer.rendering.compare import labels

    assert labels(["a", "b"], ["average", "trained"]) == ["a", "b"]
    assert labels(["a", "a", "b"], ["average", "trained", "trained"]) == [
        "a (average)", "a (trained)", "b",
    ]  # fmt: skip


def test_shared_memory_need_and_the_one_line_when_it_is_short(tmp_path):
    from trainer.training.shm import batch_bytes, check, loader_bytes, shortfall

    one = batch_bytes(400, 6)
    assert one == 6 * (400 * 400 * 17 + 24)
    # each of 2 workers keeps 4 batches ahead, the rank trains on one more; 8 ranks
    assert loader_bytes(400, 6, 2, 8) == 8 * 9 * one
    assert loader_bytes(400, 6, 0, 8) == 0  # no workers: batches stay in the rank
    assert shortfall(2**20, ranks=1, workers=2, free=2**20) is None
    why = shortfall(loader_bytes(400, 6, 2, 8), ranks=8, workers=2, free=64 * 2**20)
    assert why.startswith("/dev/shm has 64.0 MB free, and the data loaders of 8 rank(s) ")
    assert "1.1 GB" in why and "--workers" in why and "\n" not in why
    assert check(64, 2, 2, 1, where=tmp_path) is None  # a real folder with room
    assert check(64, 2, 2, 1, where=tmp_path / "none") is None  # no such folder: no check


@pytest.mark.parametrize(
    ("field", "value", "says"),
    [
        ("batch_size", 0, "--batch-size must be at least 1, not 0"),
        ("lr", 0.0, "--lr must be above 0, not 0.0"),
        ("holdout_fraction", 1.0, r"--holdout-fraction must be in \[0, 1\), not 1.0"),
        ("roughness_channels", 2, "--roughness-channels must be one of 1, 3, not 2"),
        ("max_steps", 0, "--max-steps must be at least 1, not 0"),
        ("time_limit", 0.0, "--time-limit must be above 0, not 0.0"),
        ("checkpoint_seconds", -1.0, "--checkpoint-seconds must be 0 or more, not -1.0"),
        ("checkpoint_seconds", float("nan"), "--checkpoint-seconds must be 0 or more, not nan"),
        ("loss", "l2", "--loss must be one of l1\\+vgg, l1, l1\\+msssim, l1\\+flip, not 'l2'"),
    ],
)
def test_a_bad_setting_is_refused_naming_its_flag_and_rule(field, value, says):
    from dataclasses import fields

    from trainer.training.config import RULES, TrainConfig

    assert set(RULES) <= {f.name for f in fields(TrainConfig)}
    TrainConfig(store=("s.zarr",), max_steps=None)  # the defaults pass every rule
    with pytest.raises(ValueError, match=f"^{says}$"):
        TrainConfig(store=("s.zarr",), **{field: value})


def test_an_eval_summary_gives_each_psnr_its_interval_over_materials():
    from trainer.intervals import cluster_mean
    from trainer.rendering.evaluate import Scored
    from trainer.scoring import Tally

    rng = np.random.default_rng(3)
    tally, materials, kinds = Tally(), [], []
    for m in range(9):  # 6 procedural materials, 3 uniform, 4 suns each
        kind = "procedural" if m < 6 else "uniform"
        for _ in range(4):
            row = (float(rng.normal(25 + m, 1)), 0.8, 0.2)
            for key in ("all", kind):
                tally.scores[key].append(row)
            materials.append((m % 2, m))  # (store, material)
            kinds.append(kind)
    summary = Scored([tally], materials, [], [], kinds).summary()
    psnr = np.array(tally.scores["all"])[:, 0]
    whole = cluster_mean(psnr, np.array(materials))
    o, p, u = summary["overall"], summary["by_kind"]["procedural"], summary["by_kind"]["uniform"]
    assert o["n"] == 36 and o["materials"] == 9 and p["materials"] == 6 and u["materials"] == 3
    assert (o["psnr_low"], o["psnr_high"]) == (round(whole["low"], 3), round(whole["high"], 3))
    assert o["psnr_low"] < o["psnr"] < o["psnr_high"] and p["psnr_low"] < p["psnr"] < p["psnr_high"]
    assert u["psnr_low"] is None and u["psnr_high"] is None  # 3 materials: under 5


def test_a_held_out_score_line_counts_its_materials_in_words_and_gives_an_interval_if_any():
    from trainer.training.runlog import _score_line

    rec = {"step": 6, "psnr": 19.56, "psnr_low": None, "psnr_high": None, "ssim": 0.6554,
           "samples": 5, "seconds": 0.3, "materials": 1}  # fmt: skip
    assert _score_line(rec, "") == (
        "step 6: held-out PSNR 19.56 dB over 1 material, SSIM 0.6554 (5 samples, 0.3 s)"
    )
    rec.update(materials=5, psnr_low=19.0, psnr_high=20.25)
    assert "dB [19.00, 20.25] over 5 materials, SSIM" in _score_line(rec, "")


def test_a_runs_time_counts_the_log_lines_of_the_steps_it_kept():
    """A run cut after its checkpoint at step 4 and resumed from it logs steps 5-6 again:
    the cut process's line at step 6 is dropped, so its time is not counted twice."""

    def line(step, steps, seconds):
        return {"step": step, "steps": steps, "images": 4 * steps,
                "images_per_second": 4 * steps / seconds}  # fmt: skip

    first = [line(2, 2, 1.0), line(4, 2, 1.0), line(6, 2, 9.0)]  # cut after step 6's line
    again = [line(6, 2, 2.0), line(8, 2, 2.0)]
    kept = runfiles.kept_lines([*first, {"step": 7, "steps": 0, "images_per_second": 0}, *again])
    assert [x["step"] for x in kept] == [2, 4, 6, 8] and kept[2] is again[0]
    assert runfiles.loop_seconds([*first, *again]) == pytest.approx(6.0)
    assert runfiles.loop_seconds(first) == pytest.approx(11.0)


def test_when_an_epochs_end_saves():
    """The policy alone: every epoch's end by default; with ``checkpoint_seconds``, the run's
    end, a stop, a new best score, or that long since the last checkpoint."""
    cfg = TrainConfig(store=("s",), epochs=5, max_steps=100, checkpoint_seconds=60.0)
    now = time.monotonic()

    def saves(epoch=1, step=10, timed_out=False, saved_ago=1.0, val=None, best=None, **kw):
        t = NS(epoch=epoch, step=step, timed_out=timed_out, best=best)
        log = NS(saved_at=now - saved_ago, last_val=val)
        return epoch_end_saves(dataclasses.replace(cfg, **kw), t, log)

    assert saves(checkpoint_seconds=0.0) and not saves()
    assert saves(saved_ago=61.0) and saves(epoch=5) and saves(step=100) and saves(timed_out=True)
    assert saves(val={"step": 10, "psnr": 30.0}, best={"step": 5, "psnr": 29.0})
    assert not saves(val={"step": 10, "psnr": 28.0}, best={"step": 5, "psnr": 29.0})
    assert not saves(val={"step": 9, "psnr": 31.0})  # scored before this step: not new
