"""Datasets: one module per format, all producing the same typed `Dataset`."""

from ._dataset import Dataset as Dataset
from ._dataset import Views as Views
from ._registry import load_dataset as load_dataset
