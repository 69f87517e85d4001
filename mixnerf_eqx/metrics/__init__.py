"""Image-quality and geometry metrics (numpy, float64)."""

from ._image import depth_error as depth_error
from ._image import mse_to_psnr as mse_to_psnr
from ._image import psnr as psnr
from ._image import ssim as ssim
