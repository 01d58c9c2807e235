"""Nav-camera side: frame and calibration contracts, and the frame sources (V4L2/RTSP/file/stream)."""
