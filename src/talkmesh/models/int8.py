"""int8 layers for CPU generation: weights with one scale per output row, inputs quantised row
by row, integer products summed exactly in int32 (``torch._int_mm``).

:func:`int8_layers` converts any module's linear layers and plain convolutions;
:func:`quantize_int8` is CodeTalker's recipe (which layers, and its temporal convolution's step).
"""

from __future__ import annotations

import copy

import torch
import torch.nn.functional as F
from torch import Tensor, nn


class Int8Linear(nn.Module):
    """A linear map read as int8: the weight with one scale per output row, the input quantised
    row by row (each row its own scale), integer products summed exactly in int32
    (``torch._int_mm``), then rescaled. A row's result depends on that row alone, never on the
    other rows of the batch, so a pass of fast generation quantises each frame as one frame at a
    time would (PyTorch's dynamic int8 scales the whole input together, which does not).
    ``weight`` (out, in), ``bias`` (out,) or None: the float originals are not kept."""

    def __init__(self, weight: Tensor, bias: Tensor | None) -> None:
        super().__init__()
        w = weight.detach().float()
        self.out_features, self.in_features = w.shape
        scale = w.abs().amax(1).clamp(min=1e-12) / 127
        # (in, out) as a transposed view of a contiguous (out, in) matrix: the layout
        # torch._int_mm reads fastest for one or two rows
        self.register_buffer("weight_int8", (w / scale[:, None]).round_().to(torch.int8).t())
        self.register_buffer("weight_scale", scale)
        self.register_buffer("bias", None if bias is None else bias.detach().float())

    def forward(self, x: Tensor) -> Tensor:
        rows = x.reshape(-1, self.in_features).float()
        scale = rows.abs().amax(1, keepdim=True).clamp_(min=1e-12) / 127
        y = torch._int_mm(torch.round(rows / scale).to(torch.int8), self.weight_int8).float()
        y.mul_(scale).mul_(self.weight_scale)
        if self.bias is not None:
            y.add_(self.bias)
        return y.view(*x.shape[:-1], self.out_features)

    def extra_repr(self) -> str:
        return f"in_features={self.in_features}, out_features={self.out_features}, int8"


class Int8Conv1d(nn.Module):
    """A Conv1d (zero padding, no groups or dilation) as :class:`Int8Linear` over the windows
    under its kernel: each output frame is one row, quantised on its own."""

    def __init__(self, conv: nn.Conv1d) -> None:
        super().__init__()
        # Conv1d's own attributes, which callers read (Whisper checks its stem's strides)
        self.in_channels, self.out_channels = conv.in_channels, conv.out_channels
        self.kernel_size, self.stride, self.padding = conv.kernel_size, conv.stride, conv.padding
        self.linear = Int8Linear(conv.weight.flatten(1), conv.bias)  # inputs in (c, k) order

    def forward(self, x: Tensor) -> Tensor:
        """(B, C, L) -> (B, O, L')."""
        if self.padding[0]:
            x = F.pad(x, (self.padding[0], self.padding[0]))
        windows = x.unfold(2, self.kernel_size[0], self.stride[0]).transpose(1, 2)  # (B, L', C, k)
        return self.linear(windows.flatten(2)).transpose(1, 2)


def plain_conv1d(module: nn.Module) -> bool:
    return (
        type(module) is nn.Conv1d
        and module.groups == 1
        and module.dilation[0] == 1
        and module.padding_mode == "zeros"
        and isinstance(module.padding, tuple)
    )


def int8_layers(module: nn.Module) -> nn.Module:
    """``module`` with its linear layers as :class:`Int8Linear` and its plain convolutions as
    :class:`Int8Conv1d` (a bare layer is converted itself); the float weights are not kept."""
    if type(module) is nn.Linear:
        return Int8Linear(module.weight, module.bias)
    if plain_conv1d(module):
        return Int8Conv1d(module)
    for name, child in module.named_children():
        setattr(module, name, int8_layers(child))
    return module


def quantize_int8(model: nn.Module, *, speech: bool = False, decoders: bool = True) -> nn.Module:
    """A copy of ``model`` for CPU generation whose linear layers run in int8 (:class:`Int8Linear`).

    Generating a frame at a time is bound by reading the weights; a pass over many frames by
    arithmetic. int8 helps both: 4x fewer bytes per weight, and integer products that this
    machine's CPU runs several times faster than float32 ones (VNNI). Replaced: the stage-2
    decoder blocks and output map, the VQ decoder's blocks, input and middle maps, its temporal
    convolution's per-frame step (as one matrix) and the folded feedback map; with ``speech``,
    the speech encoder's linear layers and plain convolutions (:class:`Int8Conv1d`) too. The
    per-sequence maps (audio map, cross terms, motion map) and the final vertex output map stay
    float32. Each row is quantised on its own, so a linear layer's result for a frame does not
    depend on the other frames of its pass (attention's float rounding still can, which int8
    rounding may turn into another code now and then). ``decoders=False`` with
    ``speech=True`` quantises the speech encoder alone (the decoders stay float32). Not exact:
    the effect on accuracy is measured by ``bench/fast_vs_naive.py --int8``.
    """
    out = copy.deepcopy(model).eval()
    if speech:
        out.speech = int8_layers(out.speech)
    if not decoders:
        return out
    dec = out.vqvae.decoder
    # one at a time, so that each float32 original is freed before the next copy is made
    out.blocks = int8_layers(out.blocks)
    dec.blocks = int8_layers(dec.blocks)
    out.feat_map = int8_layers(out.feat_map)
    dec.inp = int8_layers(dec.inp)
    dec.mid = int8_layers(dec.mid)
    conv = dec.conv.conv  # its per-frame step as one matrix, inputs in the (c, k) order
    dec.conv.linear = Int8Linear(conv.weight.flatten(1), conv.bias)
    out.int8 = True  # FrameGenerator quantises its folded feedback map too
    return out
