"""Evaluation metrics: PSNR, SSIM and LPIPS (AlexNet, the package's own port with shipped weights)."""
from retinexgs.evaluate.metrics import lpips_available, lpips_metric, lpips_metrics, psnr, ssim_metric

__all__ = ["lpips_available", "lpips_metric", "lpips_metrics", "psnr", "ssim_metric"]
