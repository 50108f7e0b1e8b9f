"""Evaluation metrics: PSNR, SSIM and (when available locally) LPIPS."""
from retinexgs.evaluate.metrics import lpips_available, lpips_metric, psnr, ssim_metric

__all__ = ["lpips_available", "lpips_metric", "psnr", "ssim_metric"]
