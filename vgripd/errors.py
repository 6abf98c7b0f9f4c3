"""One exception root for everything vgripd raises on purpose.

Each message names what was wrong and where (config field path, file, register, point index),
so that an operator can act on a single log line.
"""


class VgripError(Exception):
    """Root of all vgripd errors."""


class ConfigError(VgripError):
    """The configuration file is missing, unreadable or invalid (message names the field path)."""


class GeometryError(VgripError):
    """A geometric computation got inputs it cannot give a trustworthy answer for."""


class DegenerateInputError(GeometryError):
    """Too few points, collinear points, NaN, parallel rays, points behind a camera, ..."""


class ConvergenceError(GeometryError):
    """An iterative solver did not reach its tolerance (message gives the residual)."""


class ConversionError(VgripError):
    """A pose given in a vendor convention is malformed (count, number, non-unit quaternion)."""


class NotCalibratedError(VgripError):
    """A calibration the job needs is missing or invalid."""


class NotTaughtError(NotCalibratedError):
    """The object's reference pose has not been taught (yet, or again after a new hand-eye)."""


class DriverError(VgripError):
    """A device driver failed; the caller keeps running."""


class CameraError(DriverError):
    """Acquisition failed: timeout, missing file, corrupt image, device gone."""


class CameraSettingError(CameraError):
    """A camera setting the device (or driver) refuses: names the camera, feature and range."""


class LinkError(DriverError):
    """A robot/PLC link failed to start or lost its peer (message says address, port, register)."""


class CalibrationError(VgripError):
    """A calibration could not be computed or read (message names the image, sample or file)."""
