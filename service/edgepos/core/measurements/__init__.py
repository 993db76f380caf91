"""Measurement models: each maps full 8-dim states to predicted measurements with noise R."""

from edgepos.core.measurements.base import MeasurementModel, Stacked
from edgepos.core.measurements.gnss_fix import GnssPosition
from edgepos.core.measurements.gyro import GyroYawRate
from edgepos.core.measurements.rsu import RsuRange, RsuRangeBearing

__all__ = ["GnssPosition", "GyroYawRate", "MeasurementModel", "RsuRange", "RsuRangeBearing", "Stacked"]
