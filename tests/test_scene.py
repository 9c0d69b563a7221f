"""The scene's geometry buffers and the network's scene cues, the network's options beyond the
paper, the training recipes, the one-cycle schedule and the MS-SSIM loss: plain parts without
processes, and (slow) the buffers Blender renders."""

from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch
from torch.utils._python_dispatch import TorchDispatchMode

from render_jobs.screen_geometry import (
    PARTS,
    ScreenGeometry,
    camera_rays,
    camera_to_world,
    from_subsamples,
    half_width,
)
from render_jobs.screen_uv import ScreenUV, filter_taps
from render_jobs.specs import CAMERA, Sun
from render_jobs.sun import sun_lamp
from trainer.cues import CUES, cue_channels
from trainer.model import ModelConfig, NeuralRenderer, fold_batchnorm
from trainer.scene import GLOSSY_LOSS, SKY_IRRADIANCE, SceneInputs, sun_irradiance
from trainer.targets import Tonemap, light_vector, srgb_decode
from trainer.training.config import RECIPES, TrainConfig, parse_inputs, to_argv
from trainer.training.losses import RendererLoss
from trainer.training.msssim import ms_ssim, scale_weights
from trainer.training.schedule import lr_at, resumed_knee

ALL = tuple(CUES)


def geometry_at(world: dict[tuple[int, int], tuple], n: int = 4) -> ScreenGeometry:
    """Made-up buffers: pixel ``(row, col)`` sees the surface ``(world position, world
    normal, part)``; every other pixel sees sky."""
    rot = camera_to_world()
    g = {k: np.zeros((3, n, n), np.float32) for k in ("position", "normal", "tangent", "bitangent")}
    parts = np.zeros((len(PARTS), n, n), np.float32)
    parts[PARTS.index("sky")] = 1
    for (i, j), (p, normal, part) in world.items():
        g["position"][:, i, j] = (np.asarray(p) - CAMERA.location) @ rot
        g["normal"][:, i, j] = np.asarray(normal) @ rot
        parts[:, i, j] = 0
        parts[PARTS.index(part), i, j] = 1
        if part in ("ball", "ring", "core"):  # a tangent frame around the normal
            t = np.cross([0.0, 0.0, 1.0], normal)
            t = t / np.linalg.norm(t) if np.linalg.norm(t) > 0 else np.array([1.0, 0, 0])
            g["tangent"][:, i, j] = t @ rot
            g["bitangent"][:, i, j] = np.cross(normal, t) @ rot
    return ScreenGeometry(
        **g, parts=parts, camera_to_world=tuple(map(tuple, rot)),
        camera_location=CAMERA.location, half_width=half_width(),
    )  # fmt: skip


def light(direction, turbidity=3.0) -> torch.Tensor:
    return torch.from_numpy(light_vector(direction, turbidity))[None]


# ---- the geometry buffers -------------------------------------------------------------------


def test_the_camera_looks_at_its_target_from_blenders_track_to_frame():
    rot = camera_to_world()
    np.testing.assert_allclose(rot.T @ rot, np.eye(3), atol=1e-12)
    forward = np.subtract(CAMERA.look_at, CAMERA.location)
    forward /= np.linalg.norm(forward)
    np.testing.assert_allclose(-rot[:, 2], forward, atol=1e-12)  # the camera looks down -z
    assert rot[2, 1] > 0 and abs(rot[2, 0]) < 1e-12  # its up leans to world up, no roll
    centre = camera_rays(2, half_width())  # the four rays around the image centre
    np.testing.assert_allclose(centre.mean((0, 1)) / np.linalg.norm(centre.mean((0, 1))),
                               [0, 0, -1], atol=1e-12)  # fmt: skip


def test_buffers_from_subsamples_filter_each_part_and_round_trip_in_the_layout():
    s, n = 2, 4  # 2x2 sub-samples a pixel, 4² pixels
    rays = camera_rays(n * s, half_width()) @ camera_to_world().T
    world = CAMERA.location + rays * 5.0
    up = np.broadcast_to([0.0, 0.0, 1.0], world.shape)
    index = np.zeros((n * s, n * s))
    index[n:, :] = 1  # the lower half sees the floor
    index[n:, : n // 2] = 5  # its left corner the core
    g = from_subsamples(world, up, up, up, index, s, filter_taps(s))
    np.testing.assert_allclose(g.parts.sum(0), 1, atol=1e-6)
    assert g.parts[PARTS.index("sky"), 0, 0] > 0.99 and g.parts[PARTS.index("floor"), -1, -1] > 0.99
    assert g.tangent[:, 0, -1].tolist() == [0, 0, 0]  # the floor has no tangent frame
    inside = g.parts[0] < 0.01
    depth = np.linalg.norm(g.position, axis=0)[inside]
    np.testing.assert_allclose(depth, 5.0, rtol=0.01)  # the mean of points 5 m away
    layout = ScreenUV(
        uv=np.zeros((n * s, n * s, 2), np.float32), hit=index == 5, resolution=n, supersample=s,
        texture_tiling=2.0, geometry_hash="x", geometry=g,
    )  # fmt: skip
    back = ScreenUV.from_bytes(layout.to_bytes())
    for name, a in g.arrays().items():
        np.testing.assert_array_equal(getattr(back.geometry, name), a)
    assert back.geometry.meta() == g.meta()
    old = dataclasses.replace(layout, geometry=None)  # a layout rendered before the buffers
    assert ScreenUV.from_bytes(old.to_bytes()).geometry is None


@pytest.mark.slow
def test_blender_renders_the_buffers_with_the_layout(worker):
    layout = worker.screen_uv(4)
    g = layout.geometry
    assert g is not None and g.resolution == layout.resolution
    np.testing.assert_allclose(g.parts.sum(0), 1, atol=1e-5)
    material = g.parts[[PARTS.index(p) for p in ("ball", "ring", "core")]].sum(0)
    np.testing.assert_allclose(material, layout.coverage(), atol=1e-5)  # the UV render's hits
    for part in ("floor", "stand", "ball", "core", "sky"):
        assert (g.parts[PARTS.index(part)] > 0.99).any(), part
    full = g.parts[PARTS.index("sky")] < 1e-6
    seen = g.position[:, full] / np.linalg.norm(g.position[:, full], axis=0)
    rays = camera_rays(g.resolution, g.half_width).transpose(2, 0, 1)[:, full]
    assert np.abs(seen - rays).max() < 0.01  # what each pixel sees lies on its camera ray
    flat = full & (g.parts[PARTS.index("floor")] > 0.999)
    up = np.asarray(g.camera_to_world) @ g.normal[:, flat]
    np.testing.assert_allclose(up, np.broadcast_to([[0], [0], [1]], up.shape), atol=0.01)
    shell = g.parts[PARTS.index("ball")] > 0.999  # the outer shell, away from the cut's edges
    dot = (g.tangent[:, shell] * g.normal[:, shell]).sum(0)
    assert np.percentile(np.abs(dot), 99) < 0.05  # the tangent frame lies in the surface


# ---- the cues ---------------------------------------------------------------------------------


def test_the_sun_lamps_irradiance_in_torch_is_the_renderers():
    for direction, turbidity in [
        ((0.3, 0.2, 0.5), 3.0),
        ((0.1, -0.5, 0.2), 9.0),
        ((1, 0, 0.18), 6),
    ]:
        strength, colour = sun_lamp(Sun(tuple(np.asarray(direction) / np.linalg.norm(direction)),
                                        turbidity))  # fmt: skip
        got = sun_irradiance(light(direction, turbidity))[0].numpy()
        np.testing.assert_allclose(got, strength * np.asarray(colour), rtol=1e-5)


def test_shadows_of_the_ball_and_the_stand_on_the_floor_and_in_the_cut():
    g = geometry_at({
        (0, 0): ((0.0, 0.0, -1.5), (0, 0, 1), "floor"),  # under the ball
        (0, 1): ((4.0, 0.0, -1.5), (0, 0, 1), "floor"),  # far from it
        (0, 2): ((0.45, 0.0, -1.5), (0, 0, 1), "floor"),  # beside the column, under the ball
        (0, 3): ((0.0, -0.86, 0.0), (0, -1, 0), "core"),  # the core where the cut shows it
    })  # fmt: skip
    scene = SceneInputs(("shadow",), 4, 1, 1.0, g)
    overhead = scene.visibility(light((0, 0, 1))[:, :3])[0, 0]
    assert overhead[0, 0] == 0 and overhead[0, 1] == 1 and overhead[0, 2] == 0
    low = scene.visibility(light((1, 0, 0.2))[:, :3])[0, 0]  # from the side, 11° up
    assert low[0, 2] == 0  # the column shades the floor beside it
    assert low[0, 1] == 1
    tilt = np.radians(25.0)  # along the cut's tilted plane the sun reaches the core...
    along = (-np.cos(tilt) * 0.2, -0.98, np.sin(tilt) * 0.2)
    assert scene.visibility(light(along)[:, :3])[0, 0, 0, 3] == 1
    across = (0.0, -0.5, 0.87)  # ...from steeply above, the shell's upper half shades it
    assert scene.visibility(light(across)[:, :3])[0, 0, 0, 3] == 0


def test_cue_channels_painting_normals_and_shading():
    g = geometry_at({
        (1, 1): ((0.0, -1.0, 0.0), (0, -1, 0), "ball"),
        (2, 2): ((3.0, 0.0, -1.5), (0, 0, 1), "floor"),
    })  # fmt: skip
    scene = SceneInputs(ALL, 4, 1, 1.0, g)
    maps = torch.zeros(2, 10, 4, 4)
    maps[:, :3, 1, 1] = 0.8  # a light grey diffuse material, a flat normal map
    maps[:, 7:10, 1, 1] = torch.tensor([0.5, 0.5, 1.0])
    facing = light((0.0, -1.0, 0.3))  # the sun behind the camera lights the ball's front
    behind = light((0.0, 1.0, 0.3))
    out = scene(maps, torch.cat([facing, behind]))
    assert out.shape == (2, 10 + cue_channels(ALL), 4, 4) == (2, scene.out_channels, 4, 4)
    floor = g.materials["floor"]
    assert out[0, 0, 2, 2] == pytest.approx(float(_srgb(floor["diffuse"])), abs=1e-6)
    assert torch.all(out[0, :10, 0, 0] == 1)  # the sky painted white
    normal = out[:, 24:27, 1, 1]  # paint 0 + geometry 10 + light 4 after the 10 maps
    np.testing.assert_allclose(normal[0].numpy(), g.normal[:, 1, 1], atol=1e-5)
    shade = out[:, -3:]
    assert shade[0, :, 1, 1].mean() > shade[1, :, 1, 1].mean() + 0.2  # lit from the front
    assert shade[0, :, 0, 0].tolist() == pytest.approx([0.5] * 3)  # the sky is not shaded


def test_the_glossy_cue_sees_the_sky_above_the_horizon_and_the_floor_below():
    up, down = (0.0, -0.6, 0.8), (0.0, -1.0, 0.0)  # reflect the camera's view up, and down
    g = geometry_at({
        (1, 1): ((0.0, -0.6, 0.8), up, "ball"),
        (1, 2): ((0.0, -1.0, 0.0), down, "ball"),
    })  # fmt: skip
    scene = SceneInputs(("glossy",), 4, 1, 0.0, g)
    maps = torch.zeros(3, 10, 4, 4)
    maps[:, 7:10] = torch.tensor([0.5, 0.5, 1.0])[:, None, None]  # flat normal maps
    maps[:2, 3:6] = 1.0  # a white mirror, then the same as rough as it gets; then no specular
    maps[1, 6] = 1.0
    sun = light((0.3, -0.5, 0.8))
    glossy = scene(maps, sun.expand(3, -1))[:, 10:]
    tonemap = Tonemap(exposure=0.0)
    sky = tonemap(torch.full((1, 3, 1, 1), SKY_IRRADIANCE / np.pi))[0, :, 0, 0]
    floor_albedo = g.materials["floor"]["diffuse"]
    lit = sun_irradiance(sun)[0] * float(torch.nn.functional.normalize(sun[:, :3], dim=1)[0, 2])
    floor = tonemap((floor_albedo / np.pi * (lit + SKY_IRRADIANCE))[None, :, None, None])
    np.testing.assert_allclose(glossy[0, :, 1, 1], sky, rtol=1e-5)
    np.testing.assert_allclose(glossy[0, :, 1, 2], floor[0, :, 0, 0], rtol=1e-5)
    # a rough lobe loses light and sees both sides of the horizon
    sky_l, floor_l = SKY_IRRADIANCE / np.pi, floor_albedo / np.pi * (float(lit[0]) + SKY_IRRADIANCE)
    ends = [float(tonemap(torch.full((1, 3, 1, 1), (1 - GLOSSY_LOSS) * v))[0, 0, 0, 0])
            for v in sorted((sky_l, floor_l))]  # fmt: skip
    assert ends[0] < float(glossy[1, 0, 1, 1]) < ends[1]
    assert torch.all(glossy[2] == 0) and torch.all(glossy[:, :, 0, 0] == 0)  # none; the sky


def test_the_ambient_cue_lights_a_surface_by_the_sky_above_and_the_lit_floor_below():
    g = geometry_at({
        (1, 1): ((0.0, 0.0, 1.0), (0, 0, 1), "ball"),  # faces the sky
        (1, 2): ((0.0, 0.0, -1.0), (0, 0, -1), "ball"),  # faces the floor
    })  # fmt: skip
    scene = SceneInputs(("ambient",), 4, 1, 0.0, g)
    maps = torch.zeros(1, 10, 4, 4)
    maps[:, :3] = 0.8  # a light grey diffuse material with no specular, flat normal maps
    maps[:, 7:10] = torch.tensor([0.5, 0.5, 1.0])[:, None, None]
    sun = light((0.3, -0.5, 0.8))
    ambient = scene(maps, sun)[0, 10:]
    tonemap, albedo = Tonemap(exposure=0.0), srgb_decode(torch.tensor(0.8))
    lit = sun_irradiance(sun)[0] * float(torch.nn.functional.normalize(sun[:, :3], dim=1)[0, 2])
    floor = g.materials["floor"]["diffuse"] * (lit + SKY_IRRADIANCE)  # irradiance from below
    want_up = tonemap(torch.full((1, 3, 1, 1), float(albedo) / np.pi * SKY_IRRADIANCE))
    want_down = tonemap((albedo / np.pi * floor)[None, :, None, None])
    np.testing.assert_allclose(ambient[:, 1, 1], want_up[0, :, 0, 0], rtol=1e-5)
    np.testing.assert_allclose(ambient[:, 1, 2], want_down[0, :, 0, 0], rtol=1e-5)
    assert torch.all(ambient[:, 0, 0] == 0)  # the sky


@pytest.mark.parametrize("opset", [18, 11])
def test_every_cue_exports_to_onnx_and_runs_there_as_in_torch(tmp_path, opset):
    import onnxruntime

    from trainer.rendering.export import save_onnx

    g = geometry_at({
        (1, 1): ((0.0, -0.6, 0.8), (0.0, -0.6, 0.8), "ball"),
        (1, 2): ((0.0, -1.0, 0.0), (0, -1, 0), "ball"),
        (2, 2): ((3.0, 0.0, -1.5), (0, 0, 1), "floor"),
    })  # fmt: skip
    scene = SceneInputs(ALL, 4, 1, 1.0, g).eval()
    maps = torch.rand(2, 10, 4, 4, generator=torch.Generator().manual_seed(0))
    sun = torch.cat([light((0.3, -0.5, 0.8)), light((0.0, 1.0, 0.3), 7.0)])
    path = tmp_path / "cues.onnx"
    save_onnx(scene, {"maps": maps, "light": sun}, "cues", path, opset=opset)
    (got,) = onnxruntime.InferenceSession(str(path)).run(
        ["cues"], {"maps": maps.numpy(), "light": sun.numpy()}
    )
    with torch.no_grad():
        np.testing.assert_allclose(got, scene(maps, sun).numpy(), atol=1e-4)


class HostData(TorchDispatchMode):
    """Notes every tensor made from host data (``lift_fresh``: a list as an index,
    ``torch.tensor(values)``), which on a GPU is a copy that waits for the device."""

    def __init__(self):
        super().__init__()
        self.made = 0

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        self.made += func.overloadpacket.__name__ == "lift_fresh"
        return func(*args, **(kwargs or {}))


@pytest.mark.parametrize("loss", ["msssim", "flip"])
def test_a_training_step_with_every_cue_makes_no_tensor_from_host_data(loss):
    """The cues, the network, the loss and its gradients make no tensor from host data after
    the first step (which may build cached constants): on a GPU each would make the host
    wait for every step queued before it (trainer.scene's docstring)."""
    g = geometry_at({(8, 8): ((0.0, -1.0, 0.0), (0, -1, 0), "ball"),
                     (12, 4): ((3.0, 0.0, -1.5), (0, 0, 1), "floor")}, n=16)  # fmt: skip
    model = NeuralRenderer(ModelConfig(16, width=8, inputs=ALL, norm="group"), g)
    criterion = RendererLoss(None, 0.0, loss)
    maps, sun = torch.rand(2, 10, 16, 16), torch.cat([light((0.3, -0.5, 0.8))] * 2)
    for _ in range(2):
        watch = HostData()
        with watch:
            criterion(model(maps, sun), torch.rand(2, 3, 16, 16)).backward()
    assert watch.made == 0


def _srgb(x: float) -> float:
    return 12.92 * x if x <= 0.0031308 else 1.055 * x ** (1 / 2.4) - 0.055


# ---- the network's options --------------------------------------------------------------------


def test_networks_with_cues_keep_their_buffers_through_a_checkpoint():
    g = geometry_at({(1, 1): ((0.0, -1.0, 0.0), (0, -1, 0), "ball")}, n=16)
    cfg = ModelConfig(16, 8, inputs=ALL, norm="group", head=True, residual=True)
    model = NeuralRenderer(cfg, g).eval()
    assert model.encoder[0][0].in_channels == cfg.network_channels == 10 + cue_channels(ALL)
    x, lt = torch.rand(2, 10, 16, 16), torch.rand(2, 4)
    again = NeuralRenderer(cfg).eval()  # zeros until the weights are loaded
    again.load_state_dict(model.state_dict())
    with torch.no_grad():
        assert torch.equal(again(x, lt), model(x, lt))
        np.testing.assert_allclose(fold_batchnorm(model)(x, lt), model(x, lt), atol=1e-6)
    half = again.to(torch.bfloat16)
    assert half.scene.position.dtype == torch.float32  # positions keep their centimetres
    assert half(x.bfloat16(), lt.bfloat16()).dtype == torch.bfloat16


@pytest.mark.parametrize(
    "kw, says",
    [
        ({"inputs": ("glow",)}, "unknown input cue 'glow'"),
        ({"residual": True}, "add it to the inputs"),
        ({"norm": "group", "width": 12}, "multiple of 8"),
        ({"norm": "layer"}, "norm must be one of"),
        ({"arch": "zf", "inputs": ("light",)}, "paper's inputs only"),
    ],
)
def test_network_options_are_checked(kw, says):
    with pytest.raises(ValueError, match=says):
        ModelConfig(16, **{"width": 8, **kw})


def test_the_paper_network_is_the_plain_one():
    assert ModelConfig().plain and not ModelConfig(inputs=("light",)).plain
    assert not ModelConfig(norm="group").plain and not ModelConfig(head=True).plain


# ---- recipes ------------------------------------------------------------------------------------


def test_recipes_give_defaults_that_a_setting_of_ones_own_overrides(tmp_path):
    default = TrainConfig(store=("s",))
    assert default.recipe == "shaderball"
    for name, value in RECIPES["shaderball"].items():
        assert getattr(default, name) == value, name
    paper = TrainConfig(store=("s",), recipe="paper", lr=1e-2, inputs="light")
    assert (paper.width, paper.batch_size, paper.lr, paper.inputs) == (64, 6, 1e-2, ("light",))
    assert to_argv(paper)[2:] == ["--recipe", "paper", "--lr", "0.01", "--inputs", "light"]
    assert TrainConfig(store=("s",), model="zf").inputs == ()  # the baseline takes maps only
    assert TrainConfig(store=("s",), inputs="none").inputs == ()
    with pytest.raises(ValueError, match="unknown input cue"):
        parse_inputs("geometry,glow")


def test_a_config_kept_before_recipes_is_the_papers():
    kept = TrainConfig(store=("s",), recipe="paper").to_dict()
    for name in ("recipe", "inputs", "norm", "head", "residual"):
        kept.pop(name)
    back = TrainConfig.from_dict(kept)
    assert back.recipe == "paper" and back.inputs == () and back.norm == "batch"


def test_the_cli_rebuilds_a_config_from_its_argv():
    from click.testing import CliRunner

    from trainer.cli import main

    cfg = TrainConfig(store=("s",), recipe="paper", inputs="geometry,light", head=True)
    r = CliRunner().invoke(main, ["train", "--help"])
    assert "shaderball: l1+msssim; paper: l1+vgg" in " ".join(r.output.split())
    seen = {}

    def fake(cfg):  # what `trainer train` would train
        seen["cfg"] = cfg
        return {"steps": 0, "images_per_second": 0, "seconds": 0, "checkpoint": "",
                "val": None, "best": None, "timed_out": False}  # fmt: skip

    import trainer.training.train

    original, trainer.training.train.train = trainer.training.train.train, fake
    try:
        r = CliRunner().invoke(main, ["train", *to_argv(cfg)])
    finally:
        trainer.training.train.train = original
    assert r.exit_code == 0, r.output
    assert seen["cfg"] == cfg


# ---- schedule and loss ------------------------------------------------------------------------


def test_one_cycle_rises_to_its_peak_then_falls_to_zero():
    rates = [lr_at(s, 1.0, "onecycle", 100) for s in range(100)]
    assert rates[0] == pytest.approx(1 / 25, abs=0.01)
    assert max(rates) == pytest.approx(1.0) and rates.index(max(rates)) in (29, 30)
    assert rates[-1] < 1e-3 and all(a >= b for a, b in zip(rates[30:], rates[31:], strict=False))
    was = {"schedule": "onecycle", "total": 100, "knee": [30, 1.0]}
    knee = resumed_knee(60, was, 200, 0, "onecycle")  # resumed for a longer run
    assert lr_at(60, 1.0, "onecycle", 200, 0, knee) == pytest.approx(rates[60])


@pytest.mark.parametrize("side", [16, 32, 64, 128])
def test_msssim_loss_fits_small_images(side):
    weights = scale_weights(side)
    assert sum(weights) == pytest.approx(1) and len(weights) == {16: 1, 32: 2, 64: 3, 128: 4}[side]
    loss = RendererLoss(mixed="msssim")
    a = torch.rand(2, 3, side, side, requires_grad=True)
    b = torch.rand(2, 3, side, side)
    assert float(loss(b, b)) == pytest.approx(0, abs=1e-6)
    value = loss(a, b)
    value.backward()
    assert float(value.detach()) > 0.1 and torch.isfinite(a.grad).all()


@pytest.mark.parametrize("shape", [(3, 3, 128, 128), (2, 3, 64, 64), (2, 1, 48, 80)])
def test_msssim_matches_torchmetrics_in_value_and_gradient(shape):
    """The matrix-product Gaussian computes torchmetrics' MS-SSIM: the same value and gradient
    on images near and far from their targets, square or not."""
    from torchmetrics.functional.image import multiscale_structural_similarity_index_measure

    torch.manual_seed(0)
    target = torch.rand(shape)
    for noise in (0.05, 0.5):
        pred = (target + noise * torch.randn(shape)).clamp(0, 1).requires_grad_()
        betas = scale_weights(min(shape[-2:]))
        ref = multiscale_structural_similarity_index_measure(pred, target, data_range=1.0,
                                                             betas=betas)  # fmt: skip
        (ref_grad,) = torch.autograd.grad(ref, pred)
        ours = ms_ssim(pred, target)
        (grad,) = torch.autograd.grad(ours, pred)
        assert ours.item() == pytest.approx(ref.item(), abs=1e-5)
        assert torch.allclose(grad, ref_grad, atol=1e-7, rtol=1e-3)


def test_msssim_refuses_images_narrower_than_its_window():
    with pytest.raises(ValueError, match="over 5 pixels a side, not 4"):
        ms_ssim(torch.rand(1, 3, 4, 4), torch.rand(1, 3, 4, 4))
