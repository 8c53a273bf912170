"""The camera: lens models, calibration targets and board detection, chessboard corners, Zhang intrinsics with their covariance, board poses."""
