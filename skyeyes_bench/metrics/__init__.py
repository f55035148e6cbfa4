"""Metrics that match the published implementations (see docs/metrics.md).

Pure functions on arrays (PSNR, SSIM, LPIPS, Frechet distance, polynomial MMD) and mergeable
feature statistics. Feature extractors live in `skyeyes_bench.metrics.extractors`, the feature
cache in `skyeyes_bench.metrics.cache`, weight files in `skyeyes_bench.metrics.weights`.
Nothing here imports torch until a network is actually needed.
"""

from .image import lpips, psnr, ssim
from .sets import FeatureStats, frechet_distance, kernel_mmd
from .weights import MetricUnavailable

__all__ = ["psnr", "ssim", "lpips", "frechet_distance", "kernel_mmd", "FeatureStats", "MetricUnavailable"]
