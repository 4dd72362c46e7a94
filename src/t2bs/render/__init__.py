"""Renderers: the mesh rasterizer (OpenGL) and the differentiable Gaussian splat rasterizer."""
