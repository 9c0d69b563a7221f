"""An exact inference rewrite of the U-Net that never builds an upsampled tensor.

The trained network (``trainer.model``) upsamples each decoder level by bilinear x2 and
convolves the concatenation of that with the skip. Both steps are linear, so for inference:

* **Skips split.** ``conv(cat(up(z), skip), W) = conv(up(z), W_up) + conv(skip, W_skip)``:
  no concatenated tensor.
* **Sub-pixel convolution.** A 3x3 convolution of ``up(z)`` equals, for each of the four
  output phases (row parity, column parity), a 3x3 convolution of ``z`` itself with weights
  mixed by the bilinear taps (0.25 / 0.75), so one low-resolution convolution with 4x the
  output channels, then ``pixel_shuffle``. ``z`` is replicate-padded first, as the upsampling
  clamps at the edge; that is exact everywhere but the outermost ring of the output, where the
  original convolution sees its zero padding. The ring is recomputed exactly from thin strips
  of ``up(z)`` (:func:`ring`; the CPU's form). On the GPU ``z`` is zero-padded instead (the
  convolution's own padding, no padded copy written): the sub-pixel form is then wrong on the
  two outer rings, and those are corrected from the edge lines of ``z`` (:func:`zero_edges`,
  ``SubpixelRenderer.rings(edge=True)``), in one product (:func:`zero_edges_folded`,
  ``rings(edge=True, fold=True)``).
* **Light plane.** The 128 light channels are one plane repeated, so their weights are summed
  into one input channel.
* **Aligned channels** (``align=8``, for tensor cores). Tensor-core convolutions want
  channel counts that are multiples of 8; cuDNN pads others itself, a pass over the tensor
  each time. So the maps' input channels, the bottleneck's features + light plane and the
  3 output colours are padded with zero-weight channels (to 4 for a sub-pixel output
  convolution, whose 4 phases a colour make that 16 channels): the same numbers, aligned
  shapes.
  The padded input channels may hold anything finite (``trainer.rendering.infer.GraphedRenderer``
  leaves them zero); the output is sliced back to 3 channels inside the sigmoid's kernel.

The output equals the original network's up to rounding (``tests/test_trainer.py`` checks
fp32 to 1e-5) with about the same FLOPs, without the high-resolution tensors of the original
(upsampled features, concatenations, a 64-channel full-resolution input to the 3-channel
output convolution). ``trainer.rendering.infer.Renderer`` runs it in fp32 on CPU from
``trainer.rendering.infer.CPU_SUBPIXEL_FROM`` up, where it beats the folded original;
compiled in bf16 with aligned channels, its rings as edge corrections on zero-padded phases,
the encoder's convolutions and ReLUs fused, the light encoder as sums and each ring one
product (``trainer.rendering.infer.FASTEST``), it is the GPU's fastest form, batched and at
batch 1 (``benchmarks.infer``, docs/benchmarks.md). BatchNorm must be folded first
(:func:`trainer.model.fold_batchnorm`). It takes the paper's network only (no scene cues).
"""

from __future__ import annotations

import torch
import torch.nn.functional as F
from torch import nn

from trainer.model import LIGHT_CHANNELS, NeuralRenderer
from trainer.rendering.convrelu import conv_relu

# TAPS[p][a][k]: weight of the original tap k (row offset k - 1 on the upsampled grid) that
# lands on the low-resolution offset a - 1, for output phase p (2i + p), as bilinear x2
# (align_corners=False) samples rows 2i and 2i + 1 from 0.25 / 0.75 of rows i - 1, i, i + 1.
TAPS = torch.tensor(
    [
        [[0.75, 0.25, 0.0], [0.25, 0.75, 0.75], [0.0, 0.0, 0.25]],
        [[0.25, 0.0, 0.0], [0.75, 0.75, 0.25], [0.0, 0.25, 0.75]],
    ],
    dtype=torch.float64,
)


def subpixel_weight(w: torch.Tensor) -> torch.Tensor:
    """``(O, I, 3, 3)`` weights of a conv after bilinear x2 → ``(4·O, I, 3, 3)`` weights of the
    same conv at low resolution, in ``pixel_shuffle`` order (channel ``4o + 2p + q``)."""
    taps = TAPS.to(w.device)
    k = torch.einsum("pak,qbl,oikl->opqiab", taps, taps, w.double())
    return k.reshape(4 * w.shape[0], w.shape[1], 3, 3).to(w.dtype)


def ring_weight(w: torch.Tensor) -> torch.Tensor:
    """``(O, I, 3, 3)`` → the ``(2·O, I, 3, 3)`` weights :func:`ring` takes: ``w`` for the
    top and bottom rows, ``w`` transposed for the left and right columns (as strips)."""
    return torch.cat([w, w.transpose(2, 3)])


def ring(z: torch.Tensor, w2: torch.Tensor, y: torch.Tensor) -> torch.Tensor:
    """``y`` with its outer ring overwritten, in place, by the exact ``conv(up(z), w,
    padding=1)``, for a square ``z`` and ``w2 = ring_weight(w)``; returns ``y``.

    The output's first row sees the conv's zero padding and rows 0-1 of ``up(z)``, made by
    upsampling rows 0-1 of ``z`` (the clamped edge included): a strip of 3 rows convolved to
    one, and the same at the bottom. A border column is the same with rows and columns
    swapped, so the left and right columns go transposed, as rows: one upsampling of all four
    edges, then one grouped convolution (rows with ``w``, transposed columns with ``w``
    transposed); about 2/h of the sub-pixel convolution's work for a ``z`` h wide."""
    n, h = z.shape[0], z.shape[2]
    if z.shape[3] != h:
        raise ValueError(f"the ring needs a square input, not {h}x{z.shape[3]}")
    o = w2.shape[0] // 2
    firsts = torch.cat([z[:, :, :2], z[:, :, :, :2].transpose(2, 3)])  # top; left, as rows
    lasts = torch.cat([z[:, :, -2:], z[:, :, :, -2:].transpose(2, 3)])  # bottom; right
    up = F.interpolate(
        torch.cat([firsts, lasts]), scale_factor=2, mode="bilinear", align_corners=False
    )
    first, last = up[: 2 * n, :, :2], up[2 * n :, :, -2:]
    zero = torch.zeros_like(first[:, :, :1])
    a, b = torch.cat([zero, first], 2), torch.cat([last, zero], 2)  # (2n, C, 3, 2h) strips
    rows, cols = torch.cat([a[:n], b[:n]]), torch.cat([a[n:], b[n:]])
    out = F.conv2d(torch.cat([rows, cols], 1), w2, padding=(0, 1), groups=2)  # (2n, 2O, 1, 2h)
    y[:, :, :1], y[:, :, -1:] = out[:n, :o], out[n:, :o]  # top, bottom
    y[:, :, :, :1] = out[:n, o:].transpose(2, 3)  # left
    y[:, :, :, -1:] = out[n:, o:].transpose(2, 3)  # right
    return y


#: ``OUTER[e][p][k]``: ``TAPS[p][a]`` for the low-resolution tap ``a`` on edge ``e`` (0: the
#: first row or column, ``a = 0``; 1: the last, ``a = 2``) less the original tap ``k`` that
#: the zero padding hides from the output's outermost line (phase 0 at the first edge, 1 at
#: the last): what :func:`zero_edges` weighs an edge line with across the edge
OUTER = torch.stack([TAPS[:, 0], TAPS[:, 2]]) - torch.tensor(
    [[[1.0, 0, 0], [0, 0, 0]], [[0, 0, 0], [0, 0, 1.0]]], dtype=torch.float64
)


def zero_edge_weights(w: torch.Tensor) -> tuple[torch.Tensor, torch.Tensor]:
    """``(O, I, 3, 3)`` → the weights :func:`zero_edges` takes: ``(4, 3·I, 4·O)``, a matrix a
    side (top, bottom, left, right) from 3 taps along an edge line of ``z`` (rows in ``(tap,
    channel)`` order) to the 2 x 2 outputs of one low-resolution pixel of the edge (columns
    in ``(phase along, phase across, channel)`` order), and ``(4, I, 4·O)``, the corner pixels'
    terms (top-left, bottom-left, top-right, bottom-right) in the same column order."""
    taps, outer, v = TAPS.to(w.device), OUTER.to(w.device), w.double()
    o, i = w.shape[:2]
    sides = [torch.einsum("pk,qbl,ockl->bcqpo", outer[e], taps, v) for e in (0, 1)]
    sides += [torch.einsum("pak,ql,ockl->acpqo", taps, outer[e], v) for e in (0, 1)]
    corners = []
    for a, b in ((0, 0), (2, 0), (0, 2), (2, 2)):  # as each corner's two edges count it
        k = torch.einsum("pk,ql,ockl->cqpo", taps[:, a], taps[:, b], v)
        k[:, b // 2, a // 2] -= v[:, :, a, b].T  # the one tap hidden from the corner pixel
        corners.append(k.reshape(i, 4 * o))
    side = torch.stack([s.reshape(3 * i, 4 * o) for s in sides]).to(w.dtype)
    return side, torch.stack(corners).to(w.dtype)


def two_rings(d: torch.Tensor, n: int, h: int) -> torch.Tensor:
    """The sides' products ``(4, N·h, 4·O)`` (top, bottom, left, right; columns in ``(phase
    along, phase across, channel)`` order) → the ``(N, O, 2h, 2h)`` correction, zero but on
    the two outer rings."""
    d = d.view(4, n, 2 * h, 2, d.shape[2] // 4)
    rows, columns = d[:2].permute(0, 1, 4, 3, 2), d[2:].permute(0, 1, 4, 2, 3)
    far = 2 * h - 2
    return (
        F.pad(rows[0], (0, 0, 0, far))
        + F.pad(rows[1], (0, 0, far, 0))
        + F.pad(columns[0], (0, far))
        + F.pad(columns[1], (far, 0))
    )


def zero_edges(z: torch.Tensor, side: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """What ``conv(up(z), w, padding=1)`` differs by from its sub-pixel form on a
    zero-padded ``z``, for a square ``z`` h wide and ``(side, corners) =
    zero_edge_weights(w)``: the ``(N, O, 2h, 2h)`` correction to add, zero but on the two
    outer rings. The phases then convolve ``z`` with the convolution's own zero padding, so
    no level writes a padded copy of its output.

    The zero padding hides from the sub-pixel phases of the edge pixels the replicated edge
    lines that the upsampling's clamp gives them: the phases' taps on a padding line, applied
    to the edge line it repeats, 2 x 2 outputs for each pixel of the edge. Less, on the
    outermost line, the outer taps of ``w`` on the upsampled edge line, which the original
    convolution's own zero padding hides. Each side is a 3-tap product along its edge line,
    the four in one batched matrix product; each corner pixel of the padding is on two sides'
    lines, so the corners' terms go in once less, as the product's addend (a separate sum
    would make the correction read more buffers than Inductor inlines into the pointwise
    kernel that adds the level's parts)."""
    n, c, h = z.shape[:3]
    if z.shape[3] != h:
        raise ValueError(f"the ring needs a square input, not {h}x{z.shape[3]}")
    o4, last, m = corners.shape[2], h - 1, h + 2
    # each edge line of z with its ends repeated, as indices into z's pixels: one gather
    i = torch.arange(4 * m, device=z.device)
    side_of, t = i // m, (i % m - 1).clamp(0, last)
    row = torch.where(side_of == 0, 0, torch.where(side_of == 1, last, t))
    col = torch.where(side_of < 2, t, torch.where(side_of == 2, 0, last))
    at = (row * h + col).view(4, m).unfold(1, 3, 1)  # (4, h, 3): the taps along each line
    taps = z.permute(0, 2, 3, 1).reshape(n, h * h, c)[:, at]  # (N, 4, h, 3, C)
    cols = taps.transpose(0, 1).reshape(4, n * h, 3 * c)
    # the corner pixels: the top and bottom lines' middle taps at their two ends
    points = taps[:, :2, [0, last], 1].permute(2, 1, 0, 3).reshape(4, n, c)
    k = torch.bmm(points, corners)  # (4, N, 4·O): top-left, bottom-left, top-right, bottom-right
    ends = F.pad(k[:2, :, None], (0, 0, 0, last)) + F.pad(k[2:, :, None], (0, 0, last, 0))
    ends = F.pad(-ends, (0, 0, 0, 0, 0, 0, 0, 2))  # (4, N, h, 4·O): none on the columns
    return two_rings(torch.baddbmm(ends.view(4, n * h, o4), cols, side), n, h)


def folded_zero_edge_weights(side: torch.Tensor, corners: torch.Tensor) -> torch.Tensor:
    """``zero_edge_weights``' ``(side, corners)`` → ``(4, 4·I, 4·O)``: each side's matrix
    with one corner's terms (negated, as :func:`zero_edges` subtracts them) as ``I`` more
    rows, for :func:`zero_edges_folded`. A corner pixel is on two sides' lines and its
    columns are in the top and bottom sides' order (phase along the line, phase across);
    on the left and right sides the two phases swap."""
    i, o4 = corners.shape[1:]
    tl, bl, tr, br = corners  # zero_edge_weights' order

    def across(k: torch.Tensor) -> torch.Tensor:  # to a column side's (along, across) order
        return k.view(i, 2, 2, o4 // 4).transpose(1, 2).reshape(i, o4)

    extra = torch.stack([tl, br, across(bl), across(tr)])
    return torch.cat([side, -extra], 1)


def zero_edges_folded(z: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """:func:`zero_edges` as one batched matrix product (``weights =
    folded_zero_edge_weights(...)``): each side's 3 taps along its edge line and, on one
    pixel of it, a corner's value as more input columns: the top-left on the top line's
    first pixel, the bottom-right on the bottom's last, the bottom-left on the left's last,
    the top-right on the right's first. A ring is one gather and one product, where
    :func:`zero_edges` adds the corners' product, a kernel padding it into the product's
    addend and cuBLAS's copy of that addend, for a K of 4·I instead of 3·I."""
    n, c, h = z.shape[:3]
    if z.shape[3] != h:
        raise ValueError(f"the ring needs a square input, not {h}x{z.shape[3]}")
    last = h - 1
    # (side, pixel along its line, tap): taps 0-2 along the line (ends repeated), tap 3 the
    # pixel itself where it is its side's corner, else zero; indices from aranges alone, so
    # that the gather is one kernel that computes them
    dev = z.device
    side = torch.arange(4, device=dev)[:, None, None]
    along = torch.arange(h, device=dev)[None, :, None]
    tap = torch.arange(4, device=dev)[None, None, :]
    pos = (along + torch.where(tap == 3, 0, tap - 1)).clamp(0, last)
    row = torch.where(side == 0, 0, torch.where(side == 1, last, pos))
    col = torch.where(side < 2, pos, torch.where(side == 2, 0, last))
    corner = torch.where((side == 0) | (side == 3), along == 0, along == last)
    keep = (tap < 3) | corner  # (4, h, 4)
    taps = z.permute(0, 2, 3, 1).reshape(n, h * h, c)[:, row * h + col]  # (N, 4, h, 4, C)
    taps = torch.where(keep[None, :, :, :, None], taps, 0)
    cols = taps.transpose(0, 1).reshape(4, n * h, 4 * c)
    return two_rings(torch.bmm(cols, weights), n, h)


class Conv(nn.Module):
    """A 3x3 convolution with optional bias, stride and zero or replicate padding."""

    def __init__(self, weight, bias=None, stride: int = 1, pad: str = "zeros"):
        super().__init__()
        self.weight = nn.Parameter(weight.detach().clone(), requires_grad=False)
        self.bias = None if bias is None else nn.Parameter(bias.detach().clone(), False)
        self.stride, self.pad, self.fused_relu = stride, pad, False

    def relu(self, x: torch.Tensor) -> torch.Tensor:
        """``relu(self(x))``; with ``fused_relu`` (and zero padding) one operator, on CUDA one
        cuDNN call (:func:`trainer.rendering.convrelu.conv_relu`)."""
        if self.fused_relu and self.pad == "zeros":
            return conv_relu(x, self.weight, self.bias, self.stride)
        return F.relu(self(x))

    def forward(self, x: torch.Tensor, pad: str | None = None) -> torch.Tensor:
        """``pad`` overrides the padding given at construction."""
        if (pad or self.pad) == "zeros":
            return F.conv2d(x, self.weight, self.bias, self.stride, 1)
        x = F.pad(x, (1, 1, 1, 1), mode="replicate")
        return F.conv2d(x, self.weight, self.bias, self.stride)


class UpConv(nn.Module):
    """``conv(up(z), weight, padding=1)`` (no bias) of a square ``z`` without building
    ``up(z)``; its ring as :meth:`set_ring` says."""

    def __init__(self, weight: torch.Tensor):
        super().__init__()
        self.ring = nn.Parameter(ring_weight(weight.detach()), requires_grad=False)
        self.phases = Conv(subpixel_weight(weight.detach()), pad="replicate")
        self.edge = self.fold = False

    def set_ring(self, edge: bool = False, fold: bool = False) -> None:
        """The outer ring recomputed from strips of ``up(z)`` on replicate-padded phases (the
        default, :func:`ring`), or (``edge``) the phases on a zero-padded ``z`` (no padding
        pass over it) and the two outer rings corrected from the edge lines of ``z``
        (:func:`zero_edges`, whose weights are made here); ``fold`` (with ``edge``): that
        correction as one product (:func:`zero_edges_folded`)."""
        if fold and not edge:
            raise ValueError("fold is a form of the edge ring")
        self.edge, self.fold = edge, fold
        if edge and not hasattr(self, "zero_side"):
            o = self.ring.shape[0] // 2
            side, corners = zero_edge_weights(self.ring[:o].detach())
            self.zero_side = nn.Parameter(side, requires_grad=False)
            self.zero_corners = nn.Parameter(corners, requires_grad=False)
            folded = folded_zero_edge_weights(side, corners)
            self.folded = nn.Parameter(folded, requires_grad=False)

    def forward(self, z: torch.Tensor) -> torch.Tensor:
        if not self.edge:
            return ring(z, self.ring, F.pixel_shuffle(self.phases(z, "replicate"), 2))
        y = F.pixel_shuffle(self.phases(z, "zeros"), 2)
        if self.fold:
            return y + zero_edges_folded(z, self.folded)
        return y + zero_edges(z, self.zero_side, self.zero_corners)


class SubpixelLevel(nn.Module):
    """One decoder level rewritten: ``conv(cat(up(z), skip), w) + b`` as the sub-pixel
    :class:`UpConv` of ``z`` plus a convolution of the skip (none when ``skips`` is off)."""

    def __init__(self, weight: torch.Tensor, bias: torch.Tensor, skips: bool):
        super().__init__()
        feats = weight.shape[1] - (weight.shape[0] if skips else 0)  # a skip has cout channels
        self.up = UpConv(weight[:, :feats])
        self.skip = Conv(weight[:, feats:]) if skips else None
        self.bias = nn.Parameter(bias.detach().clone().view(1, -1, 1, 1), False)

    def forward(self, z: torch.Tensor, skip: torch.Tensor | None = None) -> torch.Tensor:
        y = self.up(z) + self.bias
        return y if self.skip is None else y + self.skip(skip)


class SummedMLP(nn.Module):
    """The light encoder's Tanh-MLP (``trainer.model.LightEncoder``) with each Linear layer as
    a broadcast product and a sum, in fp32 whatever the input's dtype, so that Inductor
    compiles a layer into one reduction kernel with its bias and Tanh. As matrix products
    (``nn.Linear``) a layer is an extern cuBLAS call, a copy of the bias into its output and
    a Tanh pass: three launches a layer for four values in at batch 1
    (``benchmarks.kernel_plan --batch 1`` lists Inductor's plan)."""

    def __init__(self, mlp: nn.Sequential):
        super().__init__()
        kinds = [type(m) for m in mlp]
        if kinds != [nn.Linear, nn.Tanh] * (len(kinds) // 2) or not kinds:
            raise ValueError(f"not a Linear + Tanh MLP: {kinds}")
        self.layers = nn.ModuleList(mlp[::2])

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        y = x.float()
        for layer in self.layers:
            w, b = layer.weight.float(), layer.bias.float()
            y = torch.tanh((y[:, :, None] * w.t()).sum(1) + b)
        return y.to(x.dtype)


def padded(t: torch.Tensor, dim: int, size: int) -> torch.Tensor:
    """``t`` with zeros appended along ``dim`` up to ``size``."""
    extra = size - t.shape[dim]
    return torch.cat([t, t.new_zeros(*t.shape[:dim], extra, *t.shape[dim + 1 :])], dim)


def round_up(n: int, multiple: int) -> int:
    return -(-n // multiple) * multiple


class SubpixelRenderer(nn.Module):
    """The folded network rewritten as the module docstring says; same inputs and outputs.

    ``align``: pad channel counts to multiples of it with
    zero-weight channels (1, the default, pads none; the CPU gains nothing from it).
    ``in_channels`` is the input's channel count it convolves; maps with the model's fewer
    channels are zero-padded up to it first (one extra pass: feed it ``in_channels`` to
    avoid that)."""

    def __init__(self, folded: NeuralRenderer, align: int = 1):
        super().__init__()
        if any(isinstance(block[1], nn.BatchNorm2d) for block in folded.encoder):
            raise ValueError("fold the BatchNorm first (trainer.model.fold_batchnorm)")
        self.config = cfg = folded.config
        self.light = self.mlp = folded.light.mlp  # the light encoder, as light_sums sets it
        self.b = cfg.bottleneck
        self.in_channels = round_up(cfg.in_channels, align)
        enc = [(b[0].weight, b[0].bias) for b in folded.encoder]
        enc[0] = (padded(enc[0][0], 1, self.in_channels), enc[0][1])
        self.encoder = nn.ModuleList(Conv(w, b, 2) for w, b in enc)
        fw = folded.fuse[0].weight
        deep = fw.shape[1] - LIGHT_CHANNELS  # the bottleneck's features; then the plane
        self.planes = round_up(deep + 1, align) - deep  # the plane, then zero-weight copies
        plane_w = padded(fw[:, deep:].sum(1, True), 1, self.planes)
        self.fuse = Conv(torch.cat([fw[:, :deep], plane_w], 1), folded.fuse[0].bias)
        self.dec0 = Conv(folded.decoder[0][0].weight, folded.decoder[0][0].bias)
        convs = [(b[0].weight, b[0].bias, cfg.skips) for b in folded.decoder[1:]]
        self.colours = folded.out.weight.shape[0]
        # a sub-pixel output convolution has 4 channels a colour (its phases): 4 colours
        # (3 and a zero one) make 16 channels, aligned, where 8 would make 32
        width = round_up(self.colours, max(1, align // 4))
        out_w, out_b = (padded(t, 0, width) for t in (folded.out.weight, folded.out.bias))
        convs.append((out_w, out_b, False))
        self.levels = nn.ModuleList(SubpixelLevel(w, b, skips) for w, b, skips in convs)

    def forward(self, maps: torch.Tensor, light: torch.Tensor) -> torch.Tensor:
        skips = []
        x = maps
        if x.shape[1] < self.in_channels:
            x = F.pad(x, (0, 0, 0, 0, 0, self.in_channels - x.shape[1]))
        for enc in self.encoder:
            x = enc.relu(x)
            skips.append(x)
        plane = self.light(light).view(-1, 1, self.b, self.b).to(x.dtype)
        x = F.relu(self.fuse(torch.cat([x, plane.expand(-1, self.planes, -1, -1)], 1)))
        x = self.dec0.relu(torch.cat([x, skips[-1]], 1) if self.config.skips else x)
        *decoder, out = self.levels
        for i, level in enumerate(decoder):
            x = F.relu(level(x, skips[-2 - i] if self.config.skips else None))
        return torch.sigmoid(out(x)[:, : self.colours])

    def fuse_relus(self, fused: bool = True) -> SubpixelRenderer:
        """Run the convolutions whose outputs only convolutions read (the encoder's and the
        bottleneck's last) with their ReLU in one operator (:meth:`Conv.relu`): on CUDA
        nothing rewrites their outputs; a ReLU that a pointwise kernel reads next is fused
        there by Inductor already. Returns self."""
        for conv in [*self.encoder, self.dec0]:
            conv.fused_relu = fused
        return self

    def light_sums(self, summed: bool = True) -> SubpixelRenderer:
        """Run the light encoder as :class:`SummedMLP` (``summed``) or as its Linear layers;
        returns self."""
        self.light = SummedMLP(self.mlp) if summed else self.mlp
        return self

    def rings(self, edge: bool = False, fold: bool = False) -> SubpixelRenderer:
        """Every level's ring as :meth:`UpConv.set_ring` says; returns self."""
        for module in self.modules():
            if isinstance(module, UpConv):
                module.set_ring(edge, fold)
        return self
