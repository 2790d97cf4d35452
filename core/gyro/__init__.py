"""In-use gyro calibration: bias from quasi-static windows, stillness confirmation,
pose-to-pose sensitivity, Scapellato's step-height search, and the board's high-pass inverse."""
from .bias import GyroBiasEstimator, GyroStillnessGate, WindowBias, window_bias
from .calibrate import GyroCalibration, OnlineGyroCalibrator, calibrate_gyro, gyro_report
from .conditioning import HighPassInverse, detrend_from_rest, reconstruct
from .pose import Pair, PairOutcome, PoseToPose

__all__ = ["GyroBiasEstimator", "GyroStillnessGate", "WindowBias", "window_bias", "GyroCalibration",
           "OnlineGyroCalibrator", "calibrate_gyro", "gyro_report", "HighPassInverse", "detrend_from_rest", "reconstruct",
           "Pair", "PairOutcome", "PoseToPose"]
