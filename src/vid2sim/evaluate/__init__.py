"""An asset scored on a scene: images (PSNR, SSIM, FoVVDP), material, geometry and motion."""
