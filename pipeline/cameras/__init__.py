"""Stage ``cameras``: photos → COLMAP model, undistorted images/, cameras.npz, points.ply."""
