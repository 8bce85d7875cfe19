"""Synthetic RGB-D datasets: the renderer (render), base placements (placement), clutter, and the
frame queue that renders in worker processes (frame_queue)."""
