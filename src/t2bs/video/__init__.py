"""Expression videos and multi-view video grids (paper §3.1): prompts, grid format, animator, defects."""
