"""MACs and parameters of one forward pass, counted on the executed graph: formulas, counter, op recorder.

This module is the profiler's one user of private torch APIs, kept apart so that a torch upgrade
that breaks them breaks here alone: :class:`torch.utils._python_dispatch.TorchDispatchMode` (the op
recorder), :func:`torch.utils._pytree.tree_leaves` (the tensors an op receives), and
FlopCounterMode's formula protocol (shape arguments, ``out_shape``, the ``_get_raw`` mark, sparse
``_nnz``). :mod:`benchmarks.profiler` builds the profile row and times the nets on top of it.

Compute convention (``reference/baselines.md`` section 11): the "GFLOPs" of this literature are GMACs,
one multiply-accumulate counted once, at batch 1, eval mode, each model's reference input shapes.
:func:`count_macs` counts them on the executed graph with :class:`torch.utils.flop_counter.FlopCounterMode`
(FLOPs / 2), so a module reached by two attribute paths is counted per call, never per attribute.
Only multiply-accumulate work is counted: matrix products (linear layers, attention projections, the
attention products Q K^T and A V, the gate matrix products of recurrent layers) and convolutions. Element-wise
work (activations, residual additions, BatchNorm / LayerNorm / GroupNorm, softmax, pooling, means,
the LSTM gate non-linearities) is not counted: at one operation per output element it would add under
1 % to the zoo's nets (0.1-0.6 %), except VorasNet (3.6 %: BatchNorm, ReLU and pooling on 64 x 112 x 112
maps after tiny strided convolutions).
FLOPs are reported as 2 x MACs.

Corrections to FlopCounterMode's formulas, passed as its ``custom_mapping`` (local to each count, so
torch's global formula registry is left alone):

- convolutions, transposed ones included, count output elements x in_channels / groups x kernel
  elements. That is FlopCounterMode's own count for ordinary convolutions; for a transposed
  convolution it counts *input* elements instead, 1 / stride^2 of the literature's count;
- ``mkldnn_rnn_layer`` (what ``nn.LSTM`` runs on CPU when oneDNN is available; without oneDNN the
  LSTM runs as matrix products that FlopCounterMode already counts): steps x batch x (4H x input + 4H x H)
  per layer and direction, the same as the decomposed path. A formula on the op rather than a
  module hook keeps the count on the executed graph: an LSTM called twice is counted twice, and it
  appears under its module in FlopCounterMode's per-module table like every other op;
- ``_native_multi_head_attention`` (``nn.MultiheadAttention``'s fused fast path in eval mode without
  gradients): the four E x E projections plus the two attention products, the same as the unfused path;
- ``_scaled_dot_product_flash_attention_for_cpu`` (scaled dot-product attention on CPU): the two products.

:func:`uncounted_ops` lists the ops a forward runs that neither have a formula nor are known
non-multiply-accumulate ops (:data:`NON_MAC_OPS`), so a new net cannot slip past the counter unnoticed.

Parameters (:func:`count_parameters`): the total of the net's distinct parameters, and those that an
op of one forward pass actually reads. Reading is observed at the op level (a dispatch mode that
records every tensor an op receives), not with forward hooks on modules: hooks see shared modules
once and dead modules not at all, like this, but they also miss parameters used functionally, e.g.
the output projection of ``nn.MultiheadAttention``, whose module is never called.
"""

from __future__ import annotations

import math
from collections import Counter
from collections.abc import Callable
from contextlib import ExitStack
from typing import Any

import torch
from torch import nn
from torch.utils._python_dispatch import TorchDispatchMode
from torch.utils._pytree import tree_leaves
from torch.utils.flop_counter import FlopCounterMode, flop_registry

aten = torch.ops.aten

# ------------------------------------------------------------------------------------------ MAC formulas
# Each returns FLOPs (2 x MACs), FlopCounterMode's unit; arguments arrive as shapes (FlopCounterMode's
# shape wrapper), the output shape as ``out_shape``.


def _conv_flops(x_shape, w_shape, _bias, _stride, _padding, _dilation, transposed, _output_padding, groups,
                *args, out_shape=None, **kwargs) -> int:
    """Output elements x in_channels / groups x kernel elements, for ordinary and transposed convolutions."""
    in_per_group = w_shape[0] // groups if transposed else w_shape[1]  # transposed weight: Cin x Cout/g x k
    return 2 * math.prod(out_shape) * in_per_group * math.prod(w_shape[2:])


def _rnn_layer_flops(input_shape, w_ih_shape, w_hh_shape, *args, out_shape=None, **kwargs) -> int:
    """One layer and direction of a recurrent net: steps x batch x (gates x H x (input + H))."""
    return 2 * math.prod(input_shape[:-1]) * (math.prod(w_ih_shape) + math.prod(w_hh_shape))


def _native_mha_flops(q_shape, k_shape, v_shape, embed_dim, *args, out_shape=None, **kwargs) -> int:
    """Fused multi-head attention: Q, K, V and output projections plus Q K^T and A V (batch first)."""
    batch, queries, keys = q_shape[0], q_shape[-2], k_shape[-2]
    projections = (2 * queries + 2 * keys) * embed_dim * embed_dim
    products = 2 * queries * keys * embed_dim
    return 2 * batch * (projections + products)


def _sdpa_flops(q_shape, k_shape, v_shape, *args, out_shape=None, **kwargs) -> int:
    """Scaled dot-product attention (B x H x L x D): Q K^T and A V."""
    *batch, queries, depth = q_shape
    keys, value_depth = k_shape[-2], v_shape[-1]
    return 2 * math.prod(batch) * queries * keys * (depth + value_depth)


def _vector_norm_flops(x_shape, *args, out_shape=None, **kwargs) -> int:
    """A 2-norm: one multiply-accumulate per input element."""
    return 2 * math.prod(x_shape)


def _solve_flops(a_shape, b_shape, *args, out_shape=None, **kwargs) -> int:
    """A batched linear solve by LU: n^3 / 3 for the factorisation and n^2 per right-hand side."""
    *batch, n, _ = a_shape
    columns = b_shape[-1] if len(b_shape) == len(a_shape) else 1
    return 2 * math.prod(batch) * (n ** 3 // 3 + n * n * columns)


def _mm_flops(a, b, *args, out_val=None, **kwargs) -> int:
    """A matrix product; a sparse first factor (a fixed steering matrix) costs one MAC per stored entry and
    column of the second. Gets the tensors themselves (``_get_raw``): shapes alone hide the entry count."""
    if a.layout in (torch.sparse_csr, torch.sparse_coo):
        entries = a._nnz() if a.layout == torch.sparse_coo else a.values().numel()
        return 2 * entries * b.shape[-1]
    return 2 * a.shape[0] * a.shape[1] * b.shape[1]


_mm_flops._get_raw = True  # FlopCounterMode passes tensors, not shapes, to formulas marked so

MAC_FORMULAS: dict[Any, Callable[..., int]] = {
    aten.mm: _mm_flops,
    aten.linalg_vector_norm: _vector_norm_flops,
    aten._linalg_solve_ex: _solve_flops,
    aten.convolution: _conv_flops,
    aten._convolution: _conv_flops,
    aten.convolution_overrideable: _conv_flops,
    aten.mkldnn_rnn_layer: _rnn_layer_flops,
    aten._native_multi_head_attention: _native_mha_flops,
    aten._scaled_dot_product_flash_attention_for_cpu: _sdpa_flops,
}

#: ops (aten packet names) that do no multiply-accumulate work by this convention: views and copies,
#: element-wise arithmetic and activations, reductions, normalisation, pooling, softmax, indexing
NON_MAC_OPS = frozenset({
    # views, copies, allocation
    "view", "_unsafe_view", "reshape", "t", "transpose", "permute", "unsqueeze", "squeeze", "expand", "select",
    "slice", "split", "split_with_sizes", "unsafe_split", "chunk", "unbind", "cat", "stack", "clone",
    "contiguous", "detach", "_to_copy", "copy_", "empty", "empty_like", "zeros", "zeros_like", "ones",
    "ones_like", "full", "full_like", "new_empty", "new_zeros", "arange", "alias", "lift_fresh", "index",
    "index_select", "gather",
    # element-wise
    "add", "add_", "sub", "sub_", "mul", "mul_", "div", "div_", "neg", "pow", "sqrt", "rsqrt", "exp", "log",
    "abs", "clamp", "clamp_min", "minimum", "maximum", "where", "masked_fill", "fill_", "bernoulli_",
    "relu", "relu_", "leaky_relu", "leaky_relu_", "_prelu_kernel", "gelu", "silu", "sigmoid", "sigmoid_",
    "tanh", "tanh_", "hardtanh", "eq", "ne", "lt", "le", "gt", "ge", "logical_and", "logical_or", "logical_not",
    # reductions and normalisation
    "sum", "mean", "amax", "amin", "max", "min", "argmax", "argmin", "var", "var_mean", "std",
    "native_batch_norm", "_native_batch_norm_legit_no_training", "_native_batch_norm_legit",
    "native_layer_norm", "native_group_norm", "_softmax", "_log_softmax", "softmax", "log_softmax",
    # pooling and resampling
    "max_pool2d_with_indices", "max_pool3d_with_indices", "avg_pool2d", "avg_pool3d", "_adaptive_avg_pool2d",
    "adaptive_max_pool2d", "upsample_bilinear2d", "upsample_nearest2d",
    # search: ranking, rounding, masks and small bookkeeping (srp_phat)
    "topk", "sort", "round", "floor", "ceil", "bucketize", "bitwise_and", "bitwise_or", "bitwise_not", "any",
    "isnan", "nanmedian", "rsub", "remainder", "index_put_", "scalar_tensor", "_local_scalar_dense", "diagonal",
    "eye", "squeeze_", "_linalg_check_errors", "max_pool1d", "all", "repeat", "flip", "cumsum", "abs_",
    "floor_divide", "remainder_", "take",
})


# ------------------------------------------------------------------------------------------ op recorder


_METADATA_OPS = frozenset({"size", "sym_size", "stride", "sym_stride", "dim", "numel", "sym_numel",
                           "storage_offset", "sym_storage_offset", "is_contiguous", "sym_is_contiguous",
                           "is_strides_like_format", "is_non_overlapping_and_dense", "layout", "device"})


class _OpRecorder(TorchDispatchMode):
    """Records the ops that run (by packet name) and the storages of every tensor they receive."""

    def __init__(self) -> None:
        super().__init__()
        self.ops: Counter[str] = Counter()
        self.storages: set[int] = set()

    def __torch_dispatch__(self, func, types, args=(), kwargs=None):
        kwargs = kwargs or {}
        name = getattr(getattr(func, "_overloadpacket", func), "__name__", str(func))
        if name not in _METADATA_OPS:
            self.ops[name] += 1
            for leaf in tree_leaves((args, kwargs)):
                if isinstance(leaf, torch.Tensor):
                    self.storages.add(_storage_id(leaf))
        return func(*args, **kwargs)


def _storage_id(tensor: torch.Tensor) -> int:
    try:
        return tensor.untyped_storage().data_ptr()
    except (RuntimeError, NotImplementedError):  # tensors without a plain storage (sparse, nested)
        return id(tensor)


def _call(module: nn.Module, inputs: Any) -> Any:
    """``module(*inputs)`` for a tuple of positional arguments, else ``module(inputs)`` (a zoo net's dict)."""
    return module(*inputs) if isinstance(inputs, tuple) else module(inputs)


def _evaluate(module: nn.Module, inputs: Any, *modes: Any) -> None:
    """One forward pass in eval mode without gradients under ``modes``; the training flag is restored."""
    training = module.training
    module.eval()
    prepare = getattr(module, "prepare", None)  # one-off set-up of the first call (srp_phat's null threshold)
    try:
        if prepare is not None:
            with torch.no_grad():
                prepare(inputs)
        with torch.no_grad(), ExitStack() as stack:
            for mode in modes:
                stack.enter_context(mode)
            _call(module, inputs)
    finally:
        module.train(training)


# ------------------------------------------------------------------------------------------ counts


def forward_counts(module: nn.Module, inputs: Any) -> tuple[int, int, int]:
    """MACs, total and used parameters, from one forward pass (see :func:`count_macs`, :func:`count_parameters`)."""
    counter = FlopCounterMode(display=False, custom_mapping=MAC_FORMULAS)
    recorder = _OpRecorder()
    _evaluate(module, inputs, counter, recorder)
    parameters = list(module.parameters())  # distinct: a shared parameter appears once
    total = sum(p.numel() for p in parameters)
    used = sum(p.numel() for p in parameters if _storage_id(p) in recorder.storages)
    return counter.get_total_flops() // 2, total, used


def count_macs(module: nn.Module, inputs: Any) -> int:
    """Multiply-accumulates of one forward pass (eval mode, no gradients), counted on the executed graph.

    Args:
        module: any ``nn.Module``; a zoo net takes its dict of named inputs.
        inputs: the forward's argument (a dict or tensor), or a tuple of positional arguments.
    """
    return forward_counts(module, inputs)[0]


def count_parameters(net: nn.Module, inputs: Any) -> tuple[int, int]:
    """(total, used) parameter counts: all distinct parameters, and those read by an op of one forward pass.

    A parameter is used when an executed op receives it or a view of it (eval mode, no gradients): a
    module shared by several attribute paths is counted once, a module that never runs not at all, and
    a parameter applied functionally (``F.linear(x, self.layer.weight)``) is counted although its
    module is never called.
    """
    return forward_counts(net, inputs)[1:]


def uncounted_ops(module: nn.Module, inputs: Any) -> dict[str, int]:
    """Ops a forward pass runs that have no MAC formula and are not in :data:`NON_MAC_OPS` (name -> calls).

    Empty for every zoo net; anything listed here is work that :func:`count_macs` counts as zero.
    """
    recorder = _OpRecorder()
    _evaluate(module, inputs, recorder)
    counted = {op.__name__ for op in (*flop_registry, *MAC_FORMULAS) if hasattr(op, "__name__")}
    return {name: n for name, n in sorted(recorder.ops.items()) if name not in counted | NON_MAC_OPS}
