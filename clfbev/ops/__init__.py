"""Low-level tensor ops: voxelization, sparse convolution, box utilities."""
