"""Camera calibration: ChArUco intrinsics and stereo, rectification, host stereo depth, photometric
calibration, and the calibration file format. Stands on :mod:`illuminet.runtime`.
"""
