"""CL-FusionBEV: a camera + lidar BEV 3D detector in PyTorch."""
