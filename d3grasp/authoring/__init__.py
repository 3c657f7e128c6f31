"""Reusable asset-authoring functions: mesh checks, convex decomposition, tet meshing, USD writers."""
