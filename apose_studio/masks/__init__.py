"""Target masks: prompted masks from a box or a point on a depth image (prompt) and the learned
segmentation (segment)."""
