"""Evaluation: metrics (p2p, NC, PSNR, SSIM) and the benchmark suites."""
