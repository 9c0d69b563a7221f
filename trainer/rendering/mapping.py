"""Material maps → the network's screen-space input, without Blender (torch, CPU or CUDA).

The paper's "UV-mapping pre-process": the four texture maps of a material are looked up at
the ball's UVs as the camera sees them (:class:`render_jobs.screen_uv.ScreenUV`, rendered
once from Blender) and anti-aliased with Cycles' pixel filter, which gives the stored maps a
render of that material would have (``storage.schema``: ``(11, H, W) uint8``). What Cycles
does, and so what this does, per sub-sample:

- the texture is the 8-bit map Blender loads (``render_jobs.blender.shading`` writes 8-bit
  PNGs), looked up with bilinear interpolation, repeating, at
  ``(u · 2 t, v · t)`` for texture tiling ``t`` (file row 0 is v = 1);
- diffuse and specular are sRGB bytes, interpolated as bytes and then decoded to linear;
  roughness and normal are read as they are;
- a miss (no material under the sub-sample) counts as 0.

Then every pixel is the filter-weighted mean of its sub-samples (a separable strided
convolution), colours are encoded back to sRGB and everything is rounded to 8 bits, exactly
as ``storage.schema.encode_maps`` stores the AOVs. Against Cycles' own AOVs: see
``docs/rendering.md`` ("Screen-space maps without Blender") and ``tests/test_mapping.py``.
"""

from __future__ import annotations

import warnings
from typing import NamedTuple

import numpy as np
import torch

from render_jobs.materials.maps import MAP_CHANNELS, MapBytes
from render_jobs.screen_uv import ScreenUV
from trainer.targets import srgb_decode, srgb_encode

#: texture channels, in the order of the stored maps (without the mask)
TEXTURE_CHANNELS = 10
COLOUR = slice(0, 6)  # diffuse and specular: sRGB-encoded


def _channel_groups() -> dict[str, slice]:
    out, start = {}, 0
    for name, count in MAP_CHANNELS.items():
        out[name] = slice(start, start + count)
        start += count
    return out


#: each map's channels (diffuse, specular, roughness, normal): what
#: :meth:`ScreenMapper.finish_channels` maps again alone
CHANNEL_GROUPS = _channel_groups()


def textures_from_bytes(maps: MapBytes) -> torch.Tensor:
    """A material's 8-bit maps (``MapBytes``, as Blender loads them; ``MapBytes.of`` rounds
    float maps to them) → ``(10, H, W) uint8``: diffuse, specular (sRGB-encoded),
    roughness, normal, file row 0 first (a quarter of the memory of floats)."""
    h, w = maps.size
    out = torch.empty(TEXTURE_CHANNELS, h, w, dtype=torch.uint8)
    start = 0
    for name in MAP_CHANNELS:
        part = torch.from_numpy(maps.arrays[name])
        out[start : start + part.shape[2]] = part.permute(2, 0, 1)
        start += part.shape[2]
    return out


def _bytes(x: torch.Tensor) -> torch.Tensor:
    """Values → 8-bit levels as float32 (0 to 255): :func:`_levels` of a float32 copy."""
    return _levels(x.to(torch.float32, copy=True))


def _levels(x: torch.Tensor) -> torch.Tensor:
    """``floor(clamp(x, 0, 1) · 255 + 0.5)`` in float32, in place: the torch twin of
    :func:`render_jobs.materials.maps.quantize_u8` (the textures Blender loads, the stored
    maps), ties up, bit for bit."""
    return x.clamp_(0.0, 1.0).mul_(255.0).add_(0.5).floor_()


class Corners(NamedTuple):
    """Where each hit sub-sample reads a texture: its top-left texel's index in
    :meth:`ScreenMapper.prepare`'s rows ``(hits,)``, and the weights of the texels to its
    right and below ``(hits, 1) float32``."""

    texel: torch.Tensor
    wx: torch.Tensor
    wy: torch.Tensor


class ScreenMapper:
    """Maps batches of textures to stored-map form with one :class:`ScreenUV`.

    >>> mapper = ScreenMapper(screen_uv, device="cpu")            # doctest: +SKIP
    >>> packed = mapper(textures)   # (B, 10, Ht, Wt) in [0, 1] → (B, 11, R, R) uint8

    Only the sub-samples that hit the ball are looked up, straight from the 8-bit textures
    (a gather of each one's four texels, in float64 coordinates). A sub-sample
    weighs on the 3 x 3 pixels around its own through separable taps, so the pixel filter
    is two sparse products, along x then along y (:class:`PixelFilter`): no
    super-resolution image is ever made. The layout's constant parts are built once on
    ``device``; textures of any size may come, one size per call."""

    def __init__(self, screen_uv: ScreenUV, device: str | torch.device = "cpu"):
        self.layout = screen_uv
        self.device = torch.device(device)
        self.r = screen_uv.resolution
        hit = torch.from_numpy(screen_uv.hit.reshape(-1))
        index = torch.nonzero(hit).squeeze(1)
        uv = torch.from_numpy(screen_uv.uv.reshape(-1, 2)[index.numpy()].astype(np.float64))
        tiling = screen_uv.texture_tiling
        self.st = (uv * torch.tensor([2 * tiling, tiling], dtype=torch.float64)).to(self.device)
        self.hits = len(index)
        self.filter = PixelFilter.of(screen_uv, index).to(self.device)
        ones = torch.ones(self.hits, 1, dtype=torch.float32, device=self.device)
        coverage = (self.filter @ ones).view(self.r, self.r)
        self.coverage = _levels(coverage).to(torch.uint8)
        self._kept: dict[tuple[int, int, float], Corners] = {}
        self._lut_words = _decode_table().to(self.device).view(torch.int64).view(-1)

    def _corners(self, height: int, width: int, tiling: float) -> Corners:
        """Where each hit sub-sample reads a texture of ``height`` x ``width`` repeated
        ``tiling`` times as often as the layout's own tiling (kept for the last few)."""
        key = (height, width, tiling)
        corners = self._kept.get(key)
        if corners is None:
            # texel coordinates (x along u; y down the file's rows, from 1 - v), in float64:
            # texel k's centre is at k + 0.5; the corner texel before is wrapped into
            # [0, size), the one after may be the repeated first row or column
            frac = self.st * tiling
            frac.sub_(frac.floor())  # the remainder of 1, exactly (floor is the faster op)
            x = frac[:, 0] * width - 0.5
            y = (1.0 - frac[:, 1]) * height - 0.5
            x0, y0 = x.floor(), y.floor()
            weights = torch.stack([x - x0, y - y0]).to(torch.float32)[..., None]
            x0 = x0.long().remainder_(width)
            y0 = y0.long().remainder_(height)
            corners = Corners(y0 * (width + 1) + x0, weights[0], weights[1])
            if len(self._kept) >= 4:
                self._kept.pop(next(iter(self._kept)))
            self._kept[key] = corners
        return corners

    @torch.inference_mode()
    def __call__(self, textures: torch.Tensor, tiling: float = 1.0, adjust=None) -> torch.Tensor:
        """``(B, 10, Ht, Wt)`` float textures in [0, 1] (or ``(10, Ht, Wt)``) → stored maps
        ``(B, 11, R, R) uint8`` (or ``(11, R, R)``), on ``device``: :meth:`prepare`, then
        :meth:`finish` of :meth:`lookup` (``tiling``, ``adjust``: see there)."""
        out = self.finish(self.lookup(self.prepare(textures), tiling), adjust)
        return out[0] if textures.dim() == 3 else out

    def prepare(self, textures: torch.Tensor) -> torch.Tensor:
        """The textures as Blender loads them (8-bit values), as rows of texels for the
        lookups: ``(Ht + 1, Wt + 1, B · 10) uint8`` on ``device``, texel (y, x) holding the
        B textures' 10 values, the first row and column repeated at the end (the repeat
        wrap: a lookup's four texels are then two pairs of neighbours). ``textures`` are
        floats in [0, 1] (rounded to 8 bits here) or :func:`textures_from_bytes`' uint8,
        which go to the device as bytes. Kept by callers that map one material many times
        (168 MB for a 4K material)."""
        x = textures[None] if textures.dim() == 3 else textures
        if x.dim() != 4 or x.shape[1] != TEXTURE_CHANNELS:
            raise ValueError(f"textures have shape {tuple(textures.shape)}, expected (B, 10, H, W)")
        b, c, h, w = x.shape
        x = x.to(self.device) if x.dtype == torch.uint8 else _bytes(x.to(self.device))
        out = torch.empty(h + 1, w + 1, b, c, dtype=torch.uint8, device=self.device)
        out[:h, :w] = x.permute(2, 3, 0, 1)  # one transposing copy (a cast, from floats)
        out[:h, w] = out[:h, 0]
        out[h] = out[0]
        return out.view(h + 1, w + 1, b * c)

    @torch.inference_mode()
    def lookup(self, prepared: torch.Tensor, tiling: float = 1.0) -> torch.Tensor:
        """Bilinear lookups of :meth:`prepare`'s textures at every hit sub-sample, colours
        then decoded to linear: ``(hits, B, 10)``. ``tiling`` repeats the textures that many
        times as often as the layout's tiling does (1: as rendered). The result depends on
        nothing else, so a caller that edits values keeps it and only :meth:`finish` runs
        again (``trainer.rendering.viewer.engine``)."""
        rows, cols, bc = prepared.shape
        at = self._corners(rows - 1, cols - 1, float(tiling))
        # a texel and its right-hand neighbour are 2 · bc bytes in a row: each of the two
        # gathers reads both (an overlapping view: no copy)
        pairs = prepared.view(-1).as_strided((rows * cols - 1, 2 * bc), (bc, 1))
        out = torch.empty(self.hits, bc, dtype=torch.float32, device=self.device)
        step = self.hits if self.device.type == "cuda" else _CHUNK
        raw = torch.empty(2, min(step, self.hits), 2 * bc, dtype=torch.uint8, device=self.device)
        floats = torch.empty(raw.shape, dtype=torch.float32, device=self.device)
        for i in range(0, self.hits, step):
            texel, n = at.texel[i : i + step], min(step, self.hits - i)
            torch.index_select(pairs, 0, texel, out=raw[0, :n])
            torch.index_select(pairs, 0, texel + cols, out=raw[1, :n])
            f = floats[:, :n].copy_(raw[:, :n]).view(2, n, 2, bc)
            across = torch.lerp(f[:, :, 0], f[:, :, 1], at.wx[i : i + n])
            torch.lerp(across[0], across[1], at.wy[i : i + n], out=out[i : i + n])
        out = out.div_(255.0).view(self.hits, -1, TEXTURE_CHANNELS)
        self._decode(out[..., COLOUR], out=out[..., COLOUR])  # reads its input first
        return out

    @torch.inference_mode()
    def finish(self, looked: torch.Tensor, adjust=None) -> torch.Tensor:
        """:meth:`lookup`'s sub-samples ``(hits, B, 10)`` → stored maps ``(B, 11, R, R)
        uint8``: ``adjust(samples)`` when given (a function of the ``(hits, B, 10)`` values,
        linear colours, roughness, normal encoded (n + 1) / 2, that gives the edited values
        and leaves its input as it is), the pixel filter, colours encoded, the coverage
        appended, 8-bit rounding."""
        hits, b, c = looked.shape
        if adjust is not None:
            looked = adjust(looked).contiguous()
        out = torch.empty(b, c + 1, self.r, self.r, dtype=torch.uint8, device=self.device)
        self._filter_to_levels(looked, COLOUR.stop, out[:, :c])
        out[:, c] = self.coverage
        return out

    @torch.inference_mode()
    def finish_channels(self, looked: torch.Tensor, channels: slice, edit=None) -> torch.Tensor:
        """The stored maps' ``channels`` alone ``(B, k, R, R) uint8``: the bytes
        :meth:`finish` gives them when its ``adjust`` gives ``edit(values)`` for these
        channels, ``edit`` being a function of their ``(hits, B, k)`` values (a view of
        ``looked``, to be left as it is) that gives the edited values. For an edit of one
        map (a slider), whose other channels are already mapped: nothing else is copied
        or filtered, and maps that are not colours skip the sRGB encode."""
        values = looked[..., channels]
        part = values.clone() if edit is None else edit(values)
        part = part.contiguous()
        b, k = part.shape[1:]
        colours = max(0, min(COLOUR.stop, channels.stop) - channels.start)  # COLOUR comes first
        out = torch.empty(b, k, self.r, self.r, dtype=torch.uint8, device=self.device)
        self._filter_to_levels(part, colours, out)
        return out

    def _filter_to_levels(self, samples: torch.Tensor, colours: int, out: torch.Tensor) -> None:
        """Sub-samples ``(hits, B, k)`` → ``out (B, k, R, R) uint8``: the pixel filter,
        the first ``colours`` channels encoded to sRGB, 8-bit rounding."""
        hits, b, k = samples.shape
        maps = (self.filter @ samples.view(hits, b * k)).view(self.r * self.r, b, k)
        if colours:
            maps[..., :colours] = srgb_encode(maps[..., :colours])
        maps = _levels(maps)
        out.copy_(maps.permute(1, 2, 0).view(b, k, self.r, self.r))  # one transposing cast

    def _decode(self, x: torch.Tensor, out: torch.Tensor) -> None:
        """sRGB decode of values in [0, 1] into ``out``, by linear interpolation in a
        4,097-entry table (off by under 1e-7: the curve's second derivative is below 4).
        Each entry's value and slope are read as one 64-bit word, with 32-bit indices: the
        fastest gather on CPU (2-4x ``take``)."""
        scaled = x * _LUT_STEPS
        i = scaled.int()
        entry = self._lut_words.index_select(0, i.reshape(-1)).view(torch.float32)
        entry = entry.view(*i.shape, 2)
        torch.addcmul(entry[..., 0], entry[..., 1], scaled.sub_(i), out=out)


_LUT_STEPS = 4096
#: hits looked up at once on CPU: the gathered bytes and their floats stay in cache between
#: the steps and are reused, where one pass over every hit allocates them afresh
#: (``benchmarks.viewer`` times a 4K material)
_CHUNK = 16384


def _decode_table() -> torch.Tensor:
    """``(_LUT_STEPS + 1, 2) float32``: the sRGB decode at ``k / _LUT_STEPS`` and its slope
    to the next entry (0 past the last, so that 1.0 needs no clamp)."""
    steps = torch.linspace(0.0, 1.0, _LUT_STEPS + 1, dtype=torch.float64)
    lut = srgb_decode(steps).to(torch.float32)
    slope = torch.cat([lut[1:] - lut[:-1], lut.new_zeros(1)])
    return torch.stack([lut, slope], 1).contiguous()


class PixelFilter:
    """Cycles' pixel filter over the hit sub-samples, as two CSR products (the filter is
    separable): ``along_x`` takes each hit sub-sample into the 3 pixel columns its x taps
    reach, in its own sub-sample row (a row of it for each (sub-sample row, pixel column)
    that any hit reaches), then ``along_y`` takes those rows into the ``R²`` pixels, 3 x S
    entries a pixel at most. That is 3 entries a hit and a few a pixel, where one product
    has 9 a hit (``benchmarks.viewer`` times both).
    ``filter @ x`` filters ``x (hits, n)`` into ``(R², n)``."""

    def __init__(self, along_x: torch.Tensor, along_y: torch.Tensor):
        self.along_x, self.along_y = along_x, along_y

    def __matmul__(self, x: torch.Tensor) -> torch.Tensor:
        return self.along_y @ (self.along_x @ x)

    def to(self, device: torch.device) -> PixelFilter:
        return PixelFilter(self.along_x.to(device), self.along_y.to(device))

    @classmethod
    def of(cls, screen_uv: ScreenUV, index: torch.Tensor) -> PixelFilter:
        """The filter of hit sub-samples ``index`` (flat indices in the sub-sample grid)."""
        s, r = screen_uv.supersample, screen_uv.resolution
        taps = torch.from_numpy(screen_uv.taps()).to(torch.float32)
        qy, qx = index // (s * r), index % (s * r)
        rows, cols, weights = _spread(qx, s, r, taps)  # sub-sample row y, pixel column x
        reached, rows = torch.unique(qy[cols] * r + rows, return_inverse=True)
        along_x = _csr(rows, cols, weights, (len(reached), len(index)))
        ry, rx = reached // r, reached % r
        pixel_rows, cols, weights = _spread(ry, s, r, taps)
        along_y = _csr(pixel_rows * r + rx[cols], cols, weights, (r * r, len(reached)))
        return cls(along_x, along_y)


def _spread(q: torch.Tensor, s: int, r: int, taps: torch.Tensor):
    """Sub-sample coordinates ``q`` along one axis → ``(pixel, item, weight)`` of the 3
    pixels each reaches with a tap, inside ``[0, r)``: the pixel's index along that axis,
    the index into ``q``, the tap."""
    items = torch.arange(len(q))
    pixels, keep, weights = [], [], []
    for d in (-1, 0, 1):
        p = q // s + d
        ok = (p >= 0) & (p < r)
        pixels.append(p[ok])
        keep.append(items[ok])
        weights.append(taps[q - s * p + s][ok])
    return torch.cat(pixels), torch.cat(keep), torch.cat(weights)


def _csr(rows: torch.Tensor, cols: torch.Tensor, values: torch.Tensor, shape) -> torch.Tensor:
    """A CSR matrix of the entries, with 32-bit indices: the CPU product otherwise converts
    64-bit ones on every call."""
    coo = torch.sparse_coo_tensor(torch.stack([rows, cols]), values, shape, check_invariants=False)
    with warnings.catch_warnings():  # "sparse CSR support is in beta"
        warnings.simplefilter("ignore", UserWarning)
        csr = coo.coalesce().to_sparse_csr()
        return torch.sparse_csr_tensor(
            csr.crow_indices().int(), csr.col_indices().int(), csr.values(), shape,
            check_invariants=False,
        )  # fmt: skip
