"""Image-quality and geometry metrics: PSNR, SSIM and depth error in numpy float64, LPIPS
(AlexNet) in JAX, and the object-masked variants of DTU's protocol.
"""

from ._image import depth_error as depth_error
from ._image import mse_to_psnr as mse_to_psnr
from ._image import psnr as psnr
from ._image import ssim as ssim
from ._lpips import lpips as lpips
from ._lpips import lpips_available as lpips_available
from ._masked import average_error as average_error
from ._masked import composite_outside_mask as composite_outside_mask
from ._masked import masked_psnr as masked_psnr
