"""Numba helpers shared by several stages' kernels: they only compute (no validation).

- :mod:`~recon_cli._kernels.hashtable`: open-addressing hash tables of int64 keys;
- :mod:`~recon_cli._kernels.unionfind`: disjoint-set forests over int arrays;
- :mod:`~recon_cli._kernels.arrays`: growing arrays inside a kernel;
- :mod:`~recon_cli._kernels.bits`: bit-level intrinsics (128-bit product, leading zeros, bit casts);
- :mod:`~recon_cli._kernels.numba_setup`: the threading layer, imported by parallel kernels.
"""
