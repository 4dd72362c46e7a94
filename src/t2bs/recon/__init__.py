"""VCDGS (paper §3.2): view-conditioned deformable Gaussian splatting that recovers per-frame
meshes (the static asset's topology, canonical view) from a multi-view video grid.

config.py (presets quick / paper), gaussians.py (static Gaussians: one per vertex + one per
face), control_points.py (FPS control points, geodesic KNN, Mahalanobis weights), lbs.py,
deform.py (DeformMLP, global SE(3), RefineMLP, ablation switches), losses.py (Huber + LPIPS or
D-SSIM), vcdgs.py (training), extract.py (outputs), commands.py (`t2bs reconstruct`).
"""
