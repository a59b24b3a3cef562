"""Tensors read from a file, copied into memory torch allocated itself.

A tensor safetensors reads lies where the file put it: its address depends on the length of the
file's JSON header. Two files with the same weights and different headers then give tensors at
different alignments, and torch's vector kernels may round the last bit of a result differently
on each. Copied into torch's own (64-byte aligned) memory, what a field computes depends on its
weights alone.
"""

from __future__ import annotations

import torch


def in_fresh_memory(tensor: torch.Tensor, dtype: torch.dtype | None = None) -> torch.Tensor:
    """A copy of ``tensor`` (as ``dtype``, default its own) in newly allocated, aligned memory.

    Parameters
    ----------
    tensor : (...) torch.Tensor
        Typically read from a file.
    dtype : torch.dtype, optional
        The copy's dtype.

    Returns
    -------
    (...) torch.Tensor
        Same shape and values, contiguous, on the same device.
    """
    out = torch.empty(tensor.shape, dtype=dtype or tensor.dtype, device=tensor.device)
    return out.copy_(tensor)
