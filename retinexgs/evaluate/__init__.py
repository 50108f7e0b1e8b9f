"""Evaluation metrics: PSNR, SSIM and (when available locally) LPIPS."""
