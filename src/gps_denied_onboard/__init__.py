"""gps-denied-onboard: GNSS-denied navigation for ArduPilot/PX4 from a nadir camera and a cached map."""

__version__ = "0.1.0"
