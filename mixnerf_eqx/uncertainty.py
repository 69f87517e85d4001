"""MixNeRF's predictive distribution and what is done with it (re-exports only): colour and
termination-distance mixtures, quantiles and intervals, their recalibration on validation views,
calibration reports, depth and point-cloud exports, and the view to capture next.

    import mixnerf_eqx as mx
    dist = mx.uncertainty.predictive(model, rays)     # or mx.predictive
    summary = mx.uncertainty.summarise(dist)
"""

from ._predictive.distribution import ColourMixture as ColourMixture
from ._predictive.distribution import IntervalLevels as IntervalLevels
from ._predictive.distribution import Predictive as Predictive
from ._predictive.distribution import PredictiveSummary as PredictiveSummary
from ._predictive.distribution import TerminationDistribution as TerminationDistribution
from ._predictive.distribution import predictive as predictive
from ._predictive.distribution import summarise as summarise
from ._predictive.exports import world_points as world_points
from ._predictive.exports import write_depth_exports as write_depth_exports
from ._predictive.next_view import ViewRanking as ViewRanking
from ._predictive.next_view import farthest_first as farthest_first
from ._predictive.next_view import next_view as next_view
from ._predictive.recalibration import Recalibration as Recalibration
from ._predictive.uncertainty import Sparsification as Sparsification
from ._predictive.uncertainty import calibration_pit as calibration_pit
from ._predictive.uncertainty import calibration_report as calibration_report
from ._predictive.uncertainty import collect_mixtures as collect_mixtures
from ._predictive.uncertainty import coverage_report as coverage_report
from ._predictive.uncertainty import fit_recalibration as fit_recalibration
from ._predictive.uncertainty import fit_temperature as fit_temperature
from ._predictive.uncertainty import interval_coverage as interval_coverage
from ._predictive.uncertainty import predict_rays as predict_rays
from ._predictive.uncertainty import predict_views as predict_views
from ._predictive.uncertainty import sparsification as sparsification
