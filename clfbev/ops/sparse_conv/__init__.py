"""Pure-torch 3D sparse convolution (submanifold and strided), for CPU and GPU.

A sparse tensor is a list of active sites ``coords (N, 4) = (batch, z, y, x)`` with features
``(N, C)``. A convolution is driven by a *rulebook*: for every output row and kernel tap k, the
input row it reads (``neighbours``, (N_out, K), with N_in standing for "none").

- ``rulebook``: building the rulebooks (submanifold and strided) from the active sites.
- ``function``: the convolution through a rulebook, an autograd function whose forward and
  backward both gather (no scatter, so results are bit-reproducible).
- ``modules``: ``SparseTensor`` and the ``SubMConv3d`` / ``SparseConv3d`` modules, laid out and
  initialised like ``nn.Conv3d``.
"""

from clfbev.ops.sparse_conv.function import apply_rulebook
from clfbev.ops.sparse_conv.modules import (
    SPCONV_AVAILABLE,
    SparseConv3d,
    SparseTensor,
    SubMConv3d,
    use_spconv,
)
from clfbev.ops.sparse_conv.rulebook import (
    Rulebook,
    TapGroup,
    decode_keys,
    encode_coords,
    strided_rulebook,
    subm_rulebook,
)

__all__ = [
    "SPCONV_AVAILABLE",
    "Rulebook",
    "SparseConv3d",
    "SparseTensor",
    "SubMConv3d",
    "TapGroup",
    "apply_rulebook",
    "decode_keys",
    "encode_coords",
    "strided_rulebook",
    "subm_rulebook",
    "use_spconv",
]
