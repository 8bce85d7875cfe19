"""apose_studio: 6D assembly pose estimation by point-cloud registration, with a browser studio."""

import os

# Open3D's OpenMP loops (RANSAC among them) draw and sum across threads, so two runs differ in the last
# bits; on one thread, its seeded RANSAC repeats exactly. Set before Open3D loads (it reads this once);
# a value the user set wins. torch sets its own thread count (segment.py).
os.environ.setdefault("OMP_NUM_THREADS", "1")
# OpenCV's decoders refuse images over this many pixels (its default is 2^30, 3 GB for a colour image):
# a second line behind safeio's header check (8192 x 8192). Read when cv2 loads.
os.environ.setdefault("OPENCV_IO_MAX_IMAGE_PIXELS", str(8192 * 8192))

__version__ = "0.1.0"
