"""Warp kernels: tactile forces, FEM strain, deformable pose and reward terms for all worlds."""
