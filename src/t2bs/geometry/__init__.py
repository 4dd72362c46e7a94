"""Meshes, cameras and mesh file formats."""
