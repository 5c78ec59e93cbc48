"""Real TMF882x sensors: import recordings, fit a sensor model to a target at known
distances, and range with it (issue 12). See ``docs/sensor.md``."""

from .fit import SensorFitOptions as SensorFitOptions
from .fit import fit_sensor as fit_sensor
from .importer import TmfImportError as TmfImportError
from .importer import import_file as import_file
from .importer import read_tmf882x_json as read_tmf882x_json
from .importer import read_tmf882x_log as read_tmf882x_log
from .ranging import range_histograms as range_histograms
from .response import SensorModelError as SensorModelError
from .response import SensorResponse as SensorResponse
from .response import expected_counts as expected_counts
from .response import load_sensor_model as load_sensor_model
