"""kinreg: drift correction and geodetic block adjustment of kinematic laser scans."""

from kinreg import _logging  # noqa: F401  (attaches the NullHandler)

__version__ = "0.1.0"
