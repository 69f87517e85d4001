"""Using a trained model (re-exports only): rendering and scoring views, empty-space skipping
with an occupancy grid, the threshold it is chosen with, camera paths, video and the web viewer.

    import mixnerf_eqx as mx
    rendered = mx.inference.render_views(model, scene.test, scene.near, scene.far)
"""

from ._inference.camera_path import camera_path as camera_path
from ._inference.camera_path import orbit_path as orbit_path
from ._inference.camera_path import spiral_path as spiral_path
from ._inference.evaluation import Evaluation as Evaluation
from ._inference.evaluation import evaluate as evaluate
from ._inference.evaluation import image_metrics as image_metrics
from ._inference.occupancy import OccupancyGrid as OccupancyGrid
from ._inference.occupancy import empty_grid as empty_grid
from ._inference.occupancy import refresh_occupancy as refresh_occupancy
from ._inference.occupancy import update_occupancy as update_occupancy
from ._inference.rendering import Rendered as Rendered
from ._inference.rendering import render_rays as render_rays
from ._inference.rendering import render_views as render_views
from ._inference.skipping import RenderCounts as RenderCounts
from ._inference.skipping import Skipping as Skipping
from ._inference.skipping import render_skipping as render_skipping
from ._inference.threshold import ThresholdChoice as ThresholdChoice
from ._inference.threshold import choose_threshold as choose_threshold
from ._inference.threshold import psnr_drop as psnr_drop
from ._inference.threshold import psnr_drop_bound as psnr_drop_bound
from ._inference.threshold import threshold_rays as threshold_rays
from ._inference.video import Video as Video
from ._inference.video import render_video as render_video
from ._inference.viewer import Viewer as Viewer
from ._inference.viewer import ViewerCamera as ViewerCamera
from ._inference.viewer import camera_of_view as camera_of_view
from ._inference.viewer import preview_image as preview_image
from ._inference.viewer import scene_facing as scene_facing
from ._inference.viewer import viewer_rays as viewer_rays
