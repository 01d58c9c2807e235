"""The asyncio service that runs the flight pipeline (installed as ``gps_denied_onboard.daemon``)."""
